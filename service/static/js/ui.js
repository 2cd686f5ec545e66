// Small DOM helpers shared by the page's modules, and how an error is shown.

/** el('p', {class: 'hint'}, 'text', child, ...): an element with attributes and children. */
export function el(tag, attributes = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attributes)) {
    if (value === false || value === null || value === undefined) continue;
    if (name.startsWith('on')) node.addEventListener(name.slice(2), value);
    else node.setAttribute(name, value === true ? '' : value);
  }
  for (const child of children.flat()) {
    if (child !== null && child !== undefined) node.append(child instanceof Node ? child : String(child));
  }
  return node;
}

/**
 * Show an error in ``box`` (an element with class "error"): the page's own sentence, then the
 * API's ``detail`` verbatim: a string as it is, FastAPI's 422 list as one line per entry
 * (``loc``: ``msg``), anything else as JSON.
 */
export function showError(box, error) {
  box.replaceChildren(el('p', {class: 'message'}, error.message || String(error)));
  const detail = error.detail;
  if (Array.isArray(detail)) {
    box.append(el('ul', {class: 'detail'}, detail.map((item) => el('li', {},
      item && item.loc ? `${item.loc.join('.')}: ${item.msg}` : JSON.stringify(item)))));
  } else if (typeof detail === 'string' && detail) {
    box.append(el('p', {class: 'detail'}, detail));
  } else if (detail !== null && detail !== undefined) {
    box.append(el('p', {class: 'detail'}, JSON.stringify(detail)));
  }
  box.hidden = false;
}

export function clearError(box) {
  box.replaceChildren();
  box.hidden = true;
}

export function formatBytes(bytes) {
  if (bytes < 1024) return `${bytes} B`;
  const units = ['KiB', 'MiB', 'GiB'];
  let value = bytes / 1024;
  let unit = 0;
  while (value >= 1024 && unit < units.length - 1) { value /= 1024; unit += 1; }
  return `${value.toFixed(value < 10 ? 1 : 0)} ${units[unit]}`;
}

export function formatSeconds(seconds) {
  if (!Number.isFinite(seconds) || seconds < 0) return '–';
  if (seconds < 60) return `${seconds.toFixed(seconds < 10 ? 1 : 0)} s`;
  const minutes = Math.floor(seconds / 60);
  if (minutes < 60) return `${minutes} min ${Math.round(seconds % 60)} s`;
  return `${Math.floor(minutes / 60)} h ${minutes % 60} min`;
}

export const formatCount = (n) => Number(n).toLocaleString('en-US');
