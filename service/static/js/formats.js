// Reading the files the page draws: PLY clouds (the user's own file, before the service has a
// preview of it) and Wavefront OBJ meshes, into typed arrays for one BufferGeometry each.

const TYPES = {
  char: ['getInt8', 1], int8: ['getInt8', 1], uchar: ['getUint8', 1], uint8: ['getUint8', 1],
  short: ['getInt16', 2], int16: ['getInt16', 2], ushort: ['getUint16', 2], uint16: ['getUint16', 2],
  int: ['getInt32', 4], int32: ['getInt32', 4], uint: ['getUint32', 4], uint32: ['getUint32', 4],
  float: ['getFloat32', 4], float32: ['getFloat32', 4], double: ['getFloat64', 8], float64: ['getFloat64', 8],
};

/** The PLY header at the start of ``buffer``: {format, elements: [{name, count, properties}], bodyStart}. */
export function plyHeader(buffer) {
  const bytes = new Uint8Array(buffer, 0, Math.min(buffer.byteLength, 1 << 16));
  const text = new TextDecoder('latin1').decode(bytes);
  if (!/^ply\r?\n/.test(text)) throw new Error('not a PLY file (it does not start with "ply")');
  const match = /end_header\r?\n/.exec(text);
  if (!match) throw new Error('the PLY header has no end_header line');
  const header = {format: null, elements: [], bodyStart: match.index + match[0].length};
  for (const raw of text.slice(0, match.index).split(/\r?\n/)) {
    const words = raw.trim().split(/\s+/);
    if (words[0] === 'format') header.format = words[1];
    else if (words[0] === 'element') header.elements.push({name: words[1], count: Number(words[2]), properties: []});
    else if (words[0] === 'property') {
      const element = header.elements[header.elements.length - 1];
      if (!element) throw new Error('a PLY property comes before any element');
      element.properties.push(words[1] === 'list'
        ? {name: words[4], list: true, countType: words[2], itemType: words[3]}
        : {name: words[2], type: words[1]});
    }
  }
  if (!['ascii', 'binary_little_endian', 'binary_big_endian'].includes(header.format)) {
    throw new Error(`unknown PLY format ${header.format}`);
  }
  const vertex = header.elements.find((element) => element.name === 'vertex');
  if (!vertex) throw new Error('the PLY file has no vertex element');
  for (const axis of ['x', 'y', 'z']) {
    if (!vertex.properties.some((property) => property.name === axis && !property.list)) {
      throw new Error(`the PLY vertices have no ${axis}`);
    }
  }
  return header;
}

/** ``k`` sorted distinct indices drawn uniformly from 0..n-1 (all of them when k >= n). */
export function sampleIndices(n, k) {
  if (k >= n) return Uint32Array.from({length: n}, (_, i) => i);
  const chosen = new Uint32Array(k);
  let taken = 0;
  for (let i = 0; i < n && taken < k; i += 1) {
    if (Math.random() * (n - i) < k - taken) chosen[taken++] = i; // Knuth's selection sampling
  }
  return chosen;
}

/**
 * The x y z of a random sample of at most ``maxPoints`` vertices of a PLY file (ASCII, or binary
 * of either endianness): {total, indices (into the file's vertices), positions (Float32Array)}.
 */
export function readPlySample(buffer, maxPoints = 50000) {
  const header = plyHeader(buffer);
  const vertex = header.elements.find((element) => element.name === 'vertex');
  const total = vertex.count;
  const indices = sampleIndices(total, maxPoints);
  const positions = new Float32Array(indices.length * 3);
  const axes = ['x', 'y', 'z'].map((axis) => vertex.properties.findIndex((p) => p.name === axis && !p.list));

  if (header.format === 'ascii') {
    const text = new TextDecoder('latin1').decode(new Uint8Array(buffer, header.bodyStart));
    let position = 0;
    const nextLine = () => {
      const end = text.indexOf('\n', position);
      const line = text.slice(position, end < 0 ? text.length : end);
      position = end < 0 ? text.length : end + 1;
      return line;
    };
    for (const element of header.elements) {
      if (element === vertex) break;
      for (let i = 0; i < element.count; i += 1) nextLine();
    }
    let next = 0;
    for (let i = 0; i < total && next < indices.length; i += 1) {
      const line = nextLine();
      if (i !== indices[next]) continue;
      const words = line.trim().split(/\s+/);
      for (let a = 0; a < 3; a += 1) positions[next * 3 + a] = Number(words[axes[a]]);
      next += 1;
    }
    if (next < indices.length) throw new Error(`the PLY file ends after ${next} of its vertices`);
    return {total, indices, positions};
  }

  const little = header.format === 'binary_little_endian';
  const view = new DataView(buffer);
  let offset = header.bodyStart;
  const read = (type) => {
    const [getter, size] = TYPES[type] || [];
    if (!getter) throw new Error(`unknown PLY property type ${type}`);
    const value = view[getter](offset, little);
    offset += size;
    return value;
  };
  const skipElement = (element) => {
    for (let i = 0; i < element.count; i += 1) {
      for (const property of element.properties) {
        if (property.list) { const n = read(property.countType); offset += n * TYPES[property.itemType][1]; }
        else offset += TYPES[property.type][1];
      }
    }
  };
  for (const element of header.elements) {
    if (element === vertex) break;
    skipElement(element);
  }
  if (vertex.properties.some((property) => property.list)) throw new Error('list properties on PLY vertices are not supported here');
  // Fixed-size vertices: read only the sampled ones, by offset.
  const layout = [];
  let stride = 0;
  for (const property of vertex.properties) {
    if (!TYPES[property.type]) throw new Error(`unknown PLY property type ${property.type}`);
    layout.push(stride);
    stride += TYPES[property.type][1];
  }
  if (offset + stride * total > buffer.byteLength) throw new Error('the PLY file is shorter than its header says');
  const getters = axes.map((a) => TYPES[vertex.properties[a].type][0]);
  for (let s = 0; s < indices.length; s += 1) {
    const base = offset + indices[s] * stride;
    for (let a = 0; a < 3; a += 1) positions[s * 3 + a] = view[getters[a]](base + layout[axes[a]], little);
  }
  return {total, indices, positions};
}

/**
 * A Wavefront OBJ's vertices and triangles: {positions: Float32Array, index: Uint32Array}.
 * Faces may be "f a b c", "f a/t/n ...", negative (relative) indices, or polygons (fanned).
 */
export function parseObj(text) {
  const positions = [];
  const index = [];
  let start = 0;
  const polygon = [];
  while (start < text.length) {
    let end = text.indexOf('\n', start);
    if (end < 0) end = text.length;
    const first = text.charCodeAt(start);
    const second = text.charCodeAt(start + 1);
    if (first === 118 /* v */ && (second === 32 || second === 9)) {
      const words = text.slice(start + 2, end).trim().split(/\s+/);
      positions.push(+words[0], +words[1], +words[2]);
    } else if (first === 102 /* f */ && (second === 32 || second === 9)) {
      const words = text.slice(start + 2, end).trim().split(/\s+/);
      const count = positions.length / 3;
      polygon.length = 0;
      for (const word of words) {
        const i = parseInt(word, 10);
        polygon.push(i < 0 ? count + i : i - 1);
      }
      for (let k = 1; k + 1 < polygon.length; k += 1) index.push(polygon[0], polygon[k], polygon[k + 1]);
    }
    start = end + 1;
  }
  const vertexCount = positions.length / 3;
  for (const i of index) if (!(i >= 0 && i < vertexCount)) throw new Error(`the OBJ refers to vertex ${i + 1} of ${vertexCount}`);
  return {positions: new Float32Array(positions), index: new Uint32Array(index)};
}
