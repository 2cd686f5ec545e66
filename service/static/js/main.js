// The page: wires the API key, the file, the parameter form, the job being watched, its result
// in 3D, the downloads and the list of this browser's jobs.

import {ApiError, FINAL, cancelJob, getBlob, getJSON, getKey, getOpenAPI, getText, setKey, submitJob, watchJob} from './api.js';
import {buildParamForm, jobFormSchema} from './form.js';
import {parseObj, plyHeader, readPlySample} from './formats.js';
import {JobList} from './jobs.js';
import {LossChart, ProgressView} from './progress.js';
import {clearError, el, formatBytes, formatCount, showError} from './ui.js';

const MAX_INPUT_POINTS = 50000; // input points (and normals) drawn at most
const $ = (id) => document.getElementById(id);

// Every error shows in the page, also those nothing else caught.
const pageError = $('page-error');
window.addEventListener('error', (event) => showError(pageError, new Error(`Unexpected error: ${event.message}`)));
window.addEventListener('unhandledrejection', (event) => showError(pageError, event.reason instanceof Error
  ? event.reason : new Error(`Unexpected error: ${event.reason}`)));

const sessionFiles = new Map(); // job id -> the File submitted from this page session
let paramForm = null;
let watched = null; // {id, name, stop, resultShown}
let viewer = null;

const chart = new LossChart($('loss-chart'));
const progressView = new ProgressView({
  status: $('job-status'), stage: $('job-stage'), points: $('job-points'), edgeShare: $('job-edge-share'),
  elapsed: $('job-elapsed'), remaining: $('job-remaining'), bar: $('job-progress'), iterations: $('job-iterations'),
});
const jobList = new JobList($('job-list'), (id, name) => openJob(id, name));

// --- the API key -------------------------------------------------------------------------------
const keyInput = $('api-key');
keyInput.value = getKey();
keyInput.addEventListener('change', () => {
  setKey(keyInput.value.trim());
  keyInput.removeAttribute('aria-invalid');
  jobList.refresh(true);
});

function reportAuth(error) {
  if (error instanceof ApiError && error.status === 401) keyInput.setAttribute('aria-invalid', 'true');
}

// --- the file ----------------------------------------------------------------------------------
const fileInput = $('file');
const fileInfo = $('file-info');
const dropZone = $('drop-zone');

async function describeFile() {
  const file = fileInput.files[0];
  if (!file) { fileInfo.textContent = ''; return; }
  fileInfo.replaceChildren(el('strong', {}, file.name), ` · ${formatBytes(file.size)}`);
  try {
    const header = plyHeader(await file.slice(0, 1 << 16).arrayBuffer());
    const vertices = header.elements.find((element) => element.name === 'vertex').count;
    fileInfo.append(` · its header announces ${formatCount(vertices)} points (${header.format.replaceAll('_', ' ')})`);
  } catch (error) {
    fileInfo.append(el('span', {class: 'field-error'}, ` · ${error.message}: the service will most likely refuse it`));
  }
}

fileInput.addEventListener('change', describeFile);
dropZone.addEventListener('dragover', (event) => { event.preventDefault(); dropZone.classList.add('over'); });
dropZone.addEventListener('dragleave', () => dropZone.classList.remove('over'));
dropZone.addEventListener('drop', (event) => {
  event.preventDefault();
  dropZone.classList.remove('over');
  if (event.dataTransfer.files.length) {
    fileInput.files = event.dataTransfer.files;
    describeFile();
  }
});

// --- the parameters ----------------------------------------------------------------------------
async function loadForm() {
  const container = $('param-fields');
  try {
    const schema = jobFormSchema(await getOpenAPI());
    paramForm = buildParamForm(container, schema, () => {
      const changed = paramForm?.changedCount() || 0;
      $('params-changed').textContent = changed ? `(${changed} changed)` : '';
    });
    $('reset-params').addEventListener('click', () => paramForm.reset());
  } catch (error) {
    container.replaceChildren();
    const box = el('div', {class: 'error', role: 'alert'});
    container.append(box);
    showError(box, error);
  }
}

// --- submitting --------------------------------------------------------------------------------
const submitError = $('submit-error');
const submitButton = $('submit');

$('job-form').addEventListener('submit', async (event) => {
  event.preventDefault();
  clearError(submitError);
  if (keyInput.value.trim() !== getKey()) setKey(keyInput.value.trim());
  const file = fileInput.files[0];
  const problems = [];
  if (!file) problems.push({loc: ['points'], msg: 'pick a PLY file (or drop one on the box)'});
  if (!paramForm) problems.push({loc: ['parameters'], msg: 'the parameter form did not load (see above)'});
  const {fields, errors} = paramForm ? paramForm.collect() : {fields: {}, errors: []};
  for (const [name, message] of errors) problems.push({loc: [name], msg: message});
  if (problems.length) {
    const error = new Error('Not submitted: fix these first.');
    error.detail = problems;
    showError(submitError, error);
    if (errors.length) { $('params').open = true; $(`param-${errors[0][0]}`)?.focus(); }
    return;
  }
  const body = new FormData();
  body.append(paramForm.fileField, file, file.name);
  for (const [name, value] of Object.entries(fields)) body.append(name, value);
  submitButton.disabled = true;
  submitButton.textContent = 'Uploading…';
  try {
    const job = await submitJob(body);
    sessionFiles.set(job.id, file);
    jobList.add(job, file.name);
    openJob(job.id, file.name, job);
  } catch (error) {
    reportAuth(error);
    showError(submitError, error);
  } finally {
    submitButton.disabled = false;
    submitButton.textContent = 'Reconstruct';
  }
});

// --- the watched job ---------------------------------------------------------------------------
const jobError = $('job-error');
const cancelButton = $('cancel');

function openJob(id, name, job = null) {
  watched?.stop();
  clearError(jobError);
  $('job-panel').hidden = false;
  $('job-heading').replaceChildren(`Job ${name ? `${name} ` : ''}`, el('code', {}, id));
  $('result').hidden = true;
  $('job-updates').textContent = '';
  viewer?.clear();
  chart.reset(job?.params?.iterations || 0);
  progressView.reset();
  cancelButton.disabled = true;
  cancelButton.textContent = 'Cancel';
  jobList.setCurrent(id);
  const current = {id, name, resultShown: false, stop: () => {}};
  watched = current;
  if (job) onJob(job);
  current.stop = watchJob(id, {
    onJob,
    onMode: (text) => { if (watched === current) $('job-updates').textContent = `Updates: ${text}.`; },
    onError: (error, retry) => {
      if (watched !== current) return;
      reportAuth(error);
      if (retry) error.message = `${error.message} (trying again every second)`;
      showError(jobError, error);
    },
  });
}

function onJob(job) {
  if (!watched || job.id !== watched.id) return;
  if (!FINAL.has(job.status)) clearError(jobError);
  progressView.update(job);
  if (job.progress?.losses) chart.add(job.progress.iteration, job.progress.total, job.progress.losses);
  jobList.update(job);
  const active = job.status === 'queued' || job.status === 'running';
  if (cancelButton.textContent !== 'Canceling…' || !active) {
    cancelButton.disabled = !active;
    cancelButton.textContent = 'Cancel';
  }
  if (job.status === 'failed') showError(jobError, new Error(`The job failed: ${job.error || 'no reason given'}`));
  if (job.status === 'succeeded' && !watched.resultShown) {
    watched.resultShown = true;
    showResult(job, watched);
  }
}

cancelButton.addEventListener('click', async () => {
  if (!watched) return;
  cancelButton.disabled = true;
  cancelButton.textContent = 'Canceling…';
  try {
    await cancelJob(watched.id);
  } catch (error) {
    reportAuth(error);
    showError(jobError, error);
    cancelButton.textContent = 'Cancel';
    cancelButton.disabled = false;
  }
});

// --- the result --------------------------------------------------------------------------------
const viewerWrap = $('viewer-wrap');
const viewerStatus = $('viewer-status');
const viewerNote = $('viewer-note');
const toggles = {
  mesh: $('show-mesh'), edges: $('show-edges'), curves: $('show-curves'), points: $('show-points'), normals: $('show-normals'),
};
// What the person last chose for each toggle; a toggle with nothing to show is unticked meanwhile.
const preferred = Object.fromEntries(Object.entries(toggles).map(([name, box]) => [name, box.checked]));
for (const [name, box] of Object.entries(toggles)) box.addEventListener('change', () => { preferred[name] = box.checked; });
let inputSource = null; // how to get input points and normals for the shown result

async function showResult(job, current) {
  $('result').hidden = false;
  showDownloads(job);
  showCounts(job);
  viewerWrap.dataset.state = 'loading';
  const still = () => watched === current;
  try {
    if (!viewer) {
      const {Viewer} = await import('./viewer.js');
      viewer = new Viewer($('viewer'));
      for (const [name, box] of Object.entries(toggles)) box.addEventListener('change', () => toggle(name));
      $('reset-view').addEventListener('click', () => viewer.frame());
    }
    viewer.clear();
    for (const [name, box] of Object.entries(toggles)) viewer.setVisible(name, box.checked);
    viewerStatus.textContent = 'Loading the mesh…';
    const mesh = parseObj(await getText(job.links['mesh.obj']));
    if (!still()) return;
    viewer.setMesh(mesh);
    const notes = [`Mesh: ${formatCount(mesh.positions.length / 3)} vertices, ${formatCount(mesh.index.length / 3)} triangles.`];
    viewerStatus.textContent = 'Loading the edges…';
    const edges = await getJSON(job.links['edges.json']);
    if (!still()) return;
    const drawn = viewer.setEdgePoints(edges.points || []);
    notes.push(`Edge points: ${formatCount(edges.points?.length || 0)}${drawn < (edges.points?.length || 0) ? ` (${formatCount(drawn)} drawn)` : ''}.`);
    const curves = Array.isArray(edges.curves) ? edges.curves : null;
    if (curves) viewer.setCurves(curves);
    setToggle('curves', Boolean(curves));
    notes.push(curves ? `Edge curves: ${formatCount(curves.length)}.` : 'Edge curves: this service does not trace them yet.');

    inputSource = inputSourceOf(job);
    setToggle('points', Boolean(inputSource));
    setToggle('normals', Boolean(inputSource));
    notes.push(inputSource ? inputSource.note
      : 'Input points and normals: the service offers no preview.json, and this cloud was not submitted from this page session, so there is nothing to draw them from.');
    viewerNote.textContent = notes.join(' ');
    for (const name of ['points', 'normals']) if (toggles[name].checked && inputSource) await toggle(name);
    viewerStatus.textContent = '';
    viewerWrap.dataset.state = 'ready';
  } catch (error) {
    if (!still()) return;
    viewerStatus.textContent = '';
    viewerWrap.dataset.state = 'error';
    reportAuth(error);
    if (!(error instanceof ApiError)) error.message = `The 3D view could not be drawn: ${error.message}`;
    showError(jobError, error);
  }
}

function setToggle(name, available) {
  toggles[name].disabled = !available;
  toggles[name].checked = available && preferred[name];
  viewer.setVisible(name, toggles[name].checked);
  toggles[name].closest('label').classList.toggle('disabled', !available);
}

/** Where input points and normals come from: the service's preview.json, else the file picked here. */
function inputSourceOf(job) {
  if (job.links['preview.json']) {
    return {
      note: 'Input points and normals: a sample from the service (preview.json).',
      async load() {
        const preview = await getJSON(job.links['preview.json']);
        const points = new Float32Array((preview.points || []).flat());
        const normals = new Float32Array((preview.normals || []).flat());
        return {points, normals: async () => normals,
          note: `Input points and normals: ${formatCount(points.length / 3)} of ${formatCount(preview.total ?? points.length / 3)} points (preview.json).`};
      },
    };
  }
  const file = sessionFiles.get(job.id);
  if (!file) return null;
  return {
    note: `Input points and normals: from ${file.name} as picked in this page, normals from normals.json.`,
    async load() {
      const sample = readPlySample(await file.arrayBuffer(), MAX_INPUT_POINTS);
      return {
        points: sample.positions,
        async normals() {
          const all = (await getJSON(job.links['normals.json'])).normals || [];
          if (all.length !== sample.total) {
            throw new Error(`normals.json has ${all.length} normals but ${file.name} has ${sample.total} points`);
          }
          const normals = new Float32Array(sample.indices.length * 3);
          sample.indices.forEach((index, i) => normals.set(all[index], i * 3));
          return normals;
        },
        note: `Input points: ${formatCount(sample.indices.length)} of ${formatCount(sample.total)} points of ${file.name} (read in this browser); normals from normals.json.`,
      };
    },
  };
}

async function toggle(name) {
  const on = toggles[name].checked;
  if (!viewer) return;
  if (on && (name === 'points' || name === 'normals') && !viewer.has(name)) {
    const current = watched;
    toggles[name].disabled = true;
    viewerStatus.textContent = name === 'points' ? 'Loading the input points…' : 'Loading the normals…';
    try {
      inputSource.loaded ||= await inputSource.load();
      if (watched !== current) return;
      const {points, normals, note} = inputSource.loaded;
      if (name === 'points') viewer.setInputPoints(points);
      else viewer.setNormals(points, await normals());
      viewerNote.textContent = viewerNote.textContent.replace(/Input points[^]*$/, note);
    } catch (error) {
      toggles[name].checked = false;
      reportAuth(error);
      error.message = `Could not draw the ${name === 'points' ? 'input points' : 'normals'}: ${error.message}`;
      showError(jobError, error);
    } finally {
      toggles[name].disabled = false;
      viewerStatus.textContent = '';
    }
  }
  viewer.setVisible(name, toggles[name].checked);
}

function showDownloads(job) {
  const box = $('downloads');
  box.replaceChildren();
  for (const [name, href] of Object.entries(job.links || {})) {
    if (name === 'self') continue;
    const button = el('button', {type: 'button', 'data-output': name}, `Download ${name}`);
    button.addEventListener('click', async () => {
      button.disabled = true;
      try {
        // Fetched (not a plain link) so that the API key goes with it.
        const address = URL.createObjectURL(await getBlob(href));
        const link = el('a', {href: address, download: name, hidden: true});
        document.body.append(link);
        link.click();
        link.remove();
        setTimeout(() => URL.revokeObjectURL(address), 60000);
      } catch (error) {
        reportAuth(error);
        error.message = `Could not download ${name}: ${error.message}`;
        showError(jobError, error);
      } finally {
        button.disabled = false;
      }
    });
    box.append(button);
  }
}

function showCounts(job) {
  const rows = [['input points', job.points]];
  for (const [name, value] of Object.entries(job.result || {})) {
    if (value && typeof value === 'object') {
      for (const [inner, innerValue] of Object.entries(value)) rows.push([`${name}: ${inner}`, innerValue]);
    } else rows.push([name, value]);
  }
  const format = (value) => (typeof value === 'number' ? (Number.isInteger(value) ? formatCount(value) : String(Math.round(value * 1000) / 1000)) : String(value));
  $('result-table').tBodies[0].replaceChildren(...rows.map(([name, value]) =>
    el('tr', {}, el('th', {scope: 'row'}, name.replaceAll('_', ' ')), el('td', {}, format(value)))));
}

// --- start -------------------------------------------------------------------------------------
jobList.render();
jobList.refresh(true);
loadForm();
