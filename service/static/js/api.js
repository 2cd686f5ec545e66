// The API client: the key, requests with their errors, and watching a job live (Server-Sent
// Events read with fetch, falling back to polling).

const KEY_STORAGE = 'edgerecon.apiKey';
export const FINAL = new Set(['succeeded', 'failed', 'canceled']);
const POLL_MS = 1000;

export const getKey = () => localStorage.getItem(KEY_STORAGE) || '';
export function setKey(key) {
  if (key) localStorage.setItem(KEY_STORAGE, key);
  else localStorage.removeItem(KEY_STORAGE);
}

/** An answer other than 2xx (``status``, the API's ``detail``), or no answer at all (status 0). */
export class ApiError extends Error {
  constructor(status, detail, message) {
    super(message);
    this.status = status;
    this.detail = detail;
  }
}

// Paths are resolved against the page, so the page also works behind a path prefix.
export const url = (path) => new URL(String(path).replace(/^\//, ''), document.baseURI);

function headers(extra = {}) {
  const key = getKey();
  return key ? {...extra, Authorization: `Bearer ${key}`} : extra;
}

async function errorOf(response) {
  const text = await response.text().catch(() => '');
  let detail = text || null;
  try { detail = JSON.parse(text).detail ?? detail; } catch { /* not JSON: keep the text */ }
  let message = `The service answered ${response.status} ${response.statusText}`.trim() + ':';
  if (response.status === 401) {
    message = 'The API key is missing or wrong (401). Enter the key this service was started with in the "API key" field.';
  } else if (response.status === 422) {
    message = 'The service refused the parameters (422):';
  }
  return new ApiError(response.status, detail, message);
}

/** fetch() that throws ApiError for a failed request or a non-2xx answer. */
export async function request(path, {method = 'GET', body, accept, signal} = {}) {
  let response;
  try {
    response = await fetch(url(path), {method, body, signal, headers: headers(accept ? {Accept: accept} : {})});
  } catch (error) {
    if (error.name === 'AbortError') throw error;
    throw new ApiError(0, null, `The service did not answer (${error.message}): is it running?`);
  }
  if (!response.ok) throw await errorOf(response);
  return response;
}

export const submitJob = async (formData) => (await request('v1/jobs', {method: 'POST', body: formData})).json();
export const getJob = async (id, signal) => (await request(`v1/jobs/${encodeURIComponent(id)}`, {signal})).json();
export const cancelJob = (id) => request(`v1/jobs/${encodeURIComponent(id)}`, {method: 'DELETE'});
export const getJSON = async (path, signal) => (await request(path, {signal})).json();
export const getText = async (path, signal) => (await request(path, {signal})).text();
export const getBlob = async (path) => (await request(path)).blob();

export async function getOpenAPI() {
  try {
    return await (await request('openapi.json')).json();
  } catch (error) {
    error.message = `Could not read the service's schema (openapi.json), so there is no parameter form. ${error.message}`;
    throw error;
  }
}

/**
 * Watch job ``id``: ``onJob(job)`` at every change until a final state, ``onMode(text)`` says how
 * (event stream or polling), ``onError(error)`` when it cannot go on. Returns a stop function.
 *
 * First ``GET /v1/jobs/{id}/events`` (Server-Sent Events; EventSource cannot send the API key,
 * so the stream is read with fetch). When that route answers 404 or 405 (a service without
 * it), is not an event stream, or the stream breaks or ends before a final state, it polls
 * ``GET /v1/jobs/{id}`` every second instead.
 */
export function watchJob(id, {onJob, onMode, onError}) {
  const controller = new AbortController();
  const {signal} = controller;
  (async () => {
    let last = null;
    try {
      last = await streamEvents(id, signal, onJob, onMode);
    } catch (error) {
      if (signal.aborted) return;
      if (error instanceof ApiError && error.status !== 0 && error.status < 500) { onError(error); return; }
      onMode(`polling every second (the event stream broke: ${error.message})`);
    }
    if (signal.aborted || (last && FINAL.has(last.status))) return;
    await poll(id, signal, onJob, onError);
  })();
  return () => controller.abort();
}

/** Read the event stream; the last job it sent, or null when the service has no such route. */
async function streamEvents(id, signal, onJob, onMode) {
  const response = await fetch(url(`v1/jobs/${encodeURIComponent(id)}/events`), {
    signal, cache: 'no-store', headers: headers({Accept: 'text/event-stream'}),
  }).catch((error) => {
    if (error.name === 'AbortError') throw error;
    throw new ApiError(0, null, error.message);
  });
  if (response.status === 404 || response.status === 405) {
    await response.body?.cancel();
    // An unknown job is also 404 here: polling then shows the API's own answer.
    onMode('polling every second (this service has no event stream)');
    return null;
  }
  if (!response.ok) throw await errorOf(response);
  if (!(response.headers.get('content-type') || '').startsWith('text/event-stream')) {
    await response.body?.cancel();
    onMode('polling every second (the events route did not answer with an event stream)');
    return null;
  }
  onMode('live: event stream');
  let last = null;
  for await (const message of sseMessages(response.body)) {
    if (message.event && message.event !== 'job' && message.event !== 'message') continue;
    last = JSON.parse(message.data);
    onJob(last);
    if (FINAL.has(last.status)) break;
  }
  if (!last || !FINAL.has(last.status)) onMode('polling every second (the event stream ended early)');
  return last;
}

/**
 * The messages of a Server-Sent Events body: {event, data}. Lines end with \n, \r\n or \r;
 * a blank line ends a message; lines starting with ':' are comments; "data" lines are joined
 * with \n; other fields (id, retry) are ignored.
 */
export async function* sseMessages(body) {
  const reader = body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = '';
  let event = '';
  let data = [];
  try {
    for (;;) {
      const {value, done} = await reader.read();
      if (done) break;
      buffer += value;
      // A trailing \r may be the first half of \r\n: keep it for the next chunk.
      const end = buffer.endsWith('\r') ? buffer.length - 1 : buffer.length;
      const lines = buffer.slice(0, end).split(/\r\n|\r|\n/);
      buffer = lines.pop() + buffer.slice(end);
      for (const line of lines) {
        if (line === '') {
          if (data.length) yield {event, data: data.join('\n')};
          event = '';
          data = [];
          continue;
        }
        if (line.startsWith(':')) continue;
        const colon = line.indexOf(':');
        const field = colon < 0 ? line : line.slice(0, colon);
        let value = colon < 0 ? '' : line.slice(colon + 1);
        if (value.startsWith(' ')) value = value.slice(1);
        if (field === 'data') data.push(value);
        else if (field === 'event') event = value;
      }
    }
  } finally {
    reader.cancel().catch(() => {});
  }
}

async function poll(id, signal, onJob, onError) {
  let failures = 0;
  while (!signal.aborted) {
    try {
      const job = await getJob(id, signal);
      failures = 0;
      onJob(job);
      if (FINAL.has(job.status)) return;
    } catch (error) {
      if (signal.aborted) return;
      // No answer or 5xx (Redis down): say so and keep trying; any other answer is final.
      if (!(error instanceof ApiError) || (error.status !== 0 && error.status < 500)) { onError(error); return; }
      failures += 1;
      onError(error, {retrying: true, failures});
    }
    await new Promise((resolve) => setTimeout(resolve, POLL_MS));
  }
}
