// The parameter form, generated from the OpenAPI schema of POST /v1/jobs: one field per
// parameter with its type, default, bounds, choices and description; values checked against
// the same bounds before submitting; only the fields the user changed are sent.

import {el} from './ui.js';

/** The multipart body schema of ``POST /v1/jobs`` in ``openapi``, every $ref resolved. */
export function jobFormSchema(openapi) {
  const body = openapi?.paths?.['/v1/jobs']?.post?.requestBody?.content?.['multipart/form-data']?.schema;
  if (!body) throw new Error('the schema has no multipart body for POST /v1/jobs');
  return resolve(openapi, body);
}

function resolve(openapi, schema, depth = 0) {
  if (!schema || typeof schema !== 'object' || depth > 20) return schema;
  if (schema.$ref) {
    const target = schema.$ref.replace(/^#\//, '').split('/').reduce((node, key) => node?.[key], openapi);
    const {$ref, ...rest} = schema;
    return resolve(openapi, {...target, ...rest}, depth + 1);
  }
  // Optional values are written anyOf [{...}, {type: 'null'}]; a lone allOf wraps a $ref.
  for (const key of ['anyOf', 'allOf', 'oneOf']) {
    const options = schema[key]?.filter((option) => option.type !== 'null');
    if (options?.length === 1) {
      const {[key]: _, ...rest} = schema;
      return resolve(openapi, {...resolve(openapi, options[0], depth + 1), ...rest}, depth + 1);
    }
  }
  if (schema.properties) {
    const properties = {};
    for (const [name, property] of Object.entries(schema.properties)) properties[name] = resolve(openapi, property, depth + 1);
    return {...schema, properties};
  }
  return schema;
}

const isFile = (property) => property.format === 'binary' || 'contentMediaType' in property;

/** "1 ≤ x ≤ 100000", "0 < x ≤ 1000", or '' (OpenAPI 3.1 numeric exclusive bounds, or 3.0's booleans). */
export function boundsText(property) {
  const {low, high} = bounds(property);
  const left = low ? `${low.value} ${low.exclusive ? '<' : '≤'} ` : '';
  const right = high ? ` ${high.exclusive ? '<' : '≤'} ${high.value}` : '';
  return left || right ? `${left}x${right}` : '';
}

function bounds(property) {
  let low = null;
  let high = null;
  if (typeof property.exclusiveMinimum === 'number') low = {value: property.exclusiveMinimum, exclusive: true};
  else if (typeof property.minimum === 'number') low = {value: property.minimum, exclusive: property.exclusiveMinimum === true};
  if (typeof property.exclusiveMaximum === 'number') high = {value: property.exclusiveMaximum, exclusive: true};
  else if (typeof property.maximum === 'number') high = {value: property.maximum, exclusive: property.exclusiveMaximum === true};
  return {low, high};
}

/** The problem with ``text`` as a value of ``property``, or null. */
export function problem(property, text) {
  const value = text.trim();
  if (property.type === 'integer' || property.type === 'number') {
    if (value === '') return 'enter a number (or reset it to the default)';
    if (property.type === 'integer' && !/^[+-]?\d+$/.test(value)) return 'must be a whole number';
    const number = Number(value);
    if (!Number.isFinite(number)) return 'must be a finite number';
    const {low, high} = bounds(property);
    if (low && (low.exclusive ? number <= low.value : number < low.value)) {
      return `must be ${low.exclusive ? 'greater than' : 'at least'} ${low.value}`;
    }
    if (high && (high.exclusive ? number >= high.value : number > high.value)) {
      return `must be ${high.exclusive ? 'less than' : 'at most'} ${high.value}`;
    }
    return null;
  }
  if (property.enum && !property.enum.map(String).includes(value)) return `must be one of ${property.enum.join(', ')}`;
  if (typeof property.minLength === 'number' && value.length < property.minLength) return `needs at least ${property.minLength} characters`;
  if (typeof property.maxLength === 'number' && value.length > property.maxLength) return `takes at most ${property.maxLength} characters`;
  return null;
}

/**
 * Build the form's fields into ``container`` from ``schema`` (jobFormSchema's result).
 * Returns {fileField, collect(), reset(), onChange}: collect() gives {fields: {name: text}
 * of the changed values, errors: [name, message][]} and marks the fields in error.
 */
export function buildParamForm(container, schema, onChange = () => {}) {
  const fields = [];
  let fileField = null;
  container.replaceChildren();
  for (const [name, property] of Object.entries(schema.properties || {})) {
    if (isFile(property)) { fileField = fileField || name; continue; }
    const field = makeField(name, property, schema.required?.includes(name));
    field.input.addEventListener('input', () => { field.check(); onChange(); });
    field.input.addEventListener('change', () => { field.check(); onChange(); });
    fields.push(field);
    container.append(field.row);
  }
  return {
    fileField: fileField || 'points',
    collect() {
      const changed = {};
      const errors = [];
      for (const field of fields) {
        const message = field.check();
        if (message) errors.push([field.name, message]);
        else if (field.changed()) changed[field.name] = field.text();
      }
      return {fields: changed, errors};
    },
    changedCount: () => fields.filter((field) => field.changed()).length,
    reset() { for (const field of fields) field.reset(); onChange(); },
    set(name, text) {
      const field = fields.find((candidate) => candidate.name === name);
      if (field) { field.set(text); onChange(); }
    },
  };
}

function makeField(name, property, required) {
  const id = `param-${name}`;
  const hasDefault = 'default' in property;
  const title = property.title || name;
  let input;
  if (property.type === 'boolean') {
    input = el('input', {type: 'checkbox', id, name});
  } else if (Array.isArray(property.enum)) {
    input = el('select', {id, name}, property.enum.map((option) => el('option', {value: String(option)}, String(option))));
  } else if (property.type === 'integer' || property.type === 'number') {
    // Text, not type=number: the browser would turn what it cannot parse into '' silently.
    input = el('input', {type: 'text', id, name, inputmode: property.type === 'integer' ? 'numeric' : 'decimal',
      autocomplete: 'off', spellcheck: 'false'});
  } else {
    input = el('input', {type: 'text', id, name});
  }
  const describedBy = `${id}-hint`;
  input.setAttribute('aria-describedby', `${describedBy} ${id}-error`);
  const facts = [
    hasDefault ? `default ${JSON.stringify(property.default)}` : (required ? 'required' : 'optional'),
    boundsText(property),
    Array.isArray(property.enum) ? `one of ${property.enum.join(', ')}` : '',
  ].filter(Boolean).join(' · ');
  const errorLine = el('p', {class: 'field-error', id: `${id}-error`, 'aria-live': 'polite'});
  const label = el('label', {for: id}, `${title} `, el('code', {}, name));
  const hint = el('p', {class: 'hint', id: describedBy}, property.description || '', ' ', el('span', {class: 'bounds'}, `(${facts})`));
  const row = property.type === 'boolean'
    ? el('div', {class: 'param checkbox'}, input, ' ', label, hint, errorLine)
    : el('div', {class: 'param'}, label, input, hint, errorLine);

  const defaultText = hasDefault ? String(property.default) : '';
  const text = () => (property.type === 'boolean' ? String(input.checked) : input.value.trim());
  const field = {
    name, input, row, text,
    changed() {
      if (!hasDefault) return property.type === 'boolean' ? input.checked : text() !== '';
      if (property.type === 'boolean') return input.checked !== property.default;
      if (property.type === 'integer' || property.type === 'number') {
        return Number(text()) !== Number(property.default);
      }
      return text() !== defaultText;
    },
    check() {
      const empty = property.type !== 'boolean' && text() === '';
      const message = property.type === 'boolean' || (empty && !hasDefault && !required) ? null : problem(property, text());
      errorLine.textContent = message ? `${name} ${message}` : '';
      input.setAttribute('aria-invalid', message ? 'true' : 'false');
      row.classList.toggle('changed', !message && field.changed());
      return message;
    },
    set(value) {
      if (property.type === 'boolean') input.checked = value === true || value === 'true';
      else input.value = String(value);
      field.check();
    },
    reset() { field.set(hasDefault ? property.default : ''); },
  };
  field.reset();
  return field;
}
