// A running job, as it comes: status, stage, the iteration bar with elapsed and remaining time
// (from the rate of the last seconds), the edge share, and the loss curve on a canvas.

import {FINAL} from './api.js';
import {formatCount, formatSeconds} from './ui.js';

const COLOURS = {total: '#1d2329', vanish: '#1f77b4', eikonal: '#2ca02c', laplacian: '#e8590c', free_space: '#9467bd'};
const SPARE_COLOURS = ['#8c564b', '#e377c2', '#17becf', '#bcbd22', '#7f7f7f'];
const RATE_WINDOW_MS = 15000;

/** The loss terms (log scale) against iterations, redrawn at every new point. */
export class LossChart {
  constructor(canvas) {
    this.canvas = canvas;
    this.reset(0);
    new ResizeObserver(() => this.draw()).observe(canvas);
  }

  reset(total) {
    this.total = total;
    this.series = new Map(); // name -> [[iteration, value], ...]
    this.draw();
  }

  /** Add the losses reported at ``iteration`` (repeats of an iteration already drawn are ignored). */
  add(iteration, total, losses) {
    if (total) this.total = total;
    let added = false;
    for (const [name, value] of Object.entries(losses || {})) {
      if (typeof value !== 'number' || !Number.isFinite(value)) continue;
      if (!this.series.has(name)) this.series.set(name, []);
      const points = this.series.get(name);
      if (points.length && points[points.length - 1][0] >= iteration) continue;
      points.push([iteration, value]);
      added = true;
    }
    if (added) this.draw();
  }

  colour(name, index) {
    return COLOURS[name] || SPARE_COLOURS[index % SPARE_COLOURS.length];
  }

  draw() {
    const canvas = this.canvas;
    const ratio = window.devicePixelRatio || 1;
    const width = Math.max(200, canvas.clientWidth || 640);
    const height = Math.max(100, canvas.clientHeight || 200);
    if (canvas.width !== Math.round(width * ratio) || canvas.height !== Math.round(height * ratio)) {
      canvas.width = Math.round(width * ratio);
      canvas.height = Math.round(height * ratio);
    }
    const g = canvas.getContext('2d');
    g.setTransform(ratio, 0, 0, ratio, 0, 0);
    g.fillStyle = '#ffffff';
    g.fillRect(0, 0, width, height);
    g.font = '11px system-ui, sans-serif';

    const positives = [];
    for (const points of this.series.values()) for (const [, v] of points) if (v > 0) positives.push(v);
    const left = 48, right = 30, top = 22, bottom = 22;
    const plotW = width - left - right, plotH = height - top - bottom;
    g.strokeStyle = '#c9d1d9';
    g.strokeRect(left, top, plotW, plotH);
    if (!positives.length) {
      g.fillStyle = '#5b6670';
      g.fillText('The loss curve appears here once the fit reports its first losses.', left + 8, top + plotH / 2);
      return;
    }
    let low = Math.floor(Math.log10(Math.min(...positives)));
    let high = Math.ceil(Math.log10(Math.max(...positives)));
    if (high === low) { high += 1; low -= 1; }
    const maxIteration = Math.max(this.total || 1, ...[...this.series.values()].map((p) => p[p.length - 1]?.[0] || 1));
    const x = (iteration) => left + (iteration / maxIteration) * plotW;
    const y = (value) => top + (1 - (Math.log10(value) - low) / (high - low)) * plotH;

    // Decades and iteration ticks.
    g.fillStyle = '#5b6670';
    g.textAlign = 'right';
    g.textBaseline = 'middle';
    const every = Math.max(1, Math.ceil((high - low) / 6));
    for (let decade = low; decade <= high; decade += every) {
      const yy = y(10 ** decade);
      g.strokeStyle = '#eef1f4';
      g.beginPath(); g.moveTo(left, yy); g.lineTo(left + plotW, yy); g.stroke();
      g.fillText(`1e${decade}`, left - 6, yy);
    }
    g.textAlign = 'center';
    g.textBaseline = 'top';
    const step = niceStep(maxIteration / 5);
    for (let iteration = 0; iteration <= maxIteration; iteration += step) {
      g.fillText(formatCount(iteration), x(iteration), top + plotH + 5);
    }

    // The curves, then the legend.
    let index = 0;
    let legendX = left;
    g.textAlign = 'left';
    g.textBaseline = 'middle';
    for (const [name, points] of this.series) {
      const colour = this.colour(name, index++);
      g.strokeStyle = colour;
      g.fillStyle = colour;
      g.lineWidth = name === 'total' ? 2 : 1.4;
      g.beginPath();
      let drawing = false;
      for (const [iteration, value] of points) {
        if (!(value > 0)) { drawing = false; continue; } // log scale: zero is off the chart
        if (drawing) g.lineTo(x(iteration), y(value));
        else g.moveTo(x(iteration), y(value));
        drawing = true;
      }
      g.stroke();
      const last = points[points.length - 1];
      if (last && last[1] > 0) { g.beginPath(); g.arc(x(last[0]), y(last[1]), 2.5, 0, 2 * Math.PI); g.fill(); }
      g.fillRect(legendX, 7, 14, 3);
      g.fillStyle = '#1d2329';
      g.fillText(name, legendX + 18, 9);
      legendX += 30 + g.measureText(name).width;
    }
    g.lineWidth = 1;
  }
}

/** 1, 2 or 5 times a power of ten, at least ``rough`` (and at least 1). */
function niceStep(rough) {
  const power = 10 ** Math.floor(Math.log10(Math.max(1, rough)));
  return [1, 2, 5, 10].map((m) => m * power).find((candidate) => candidate >= rough) || power * 10;
}

/** The job's status lines, progress bar, elapsed and remaining time. */
export class ProgressView {
  constructor(elements) {
    this.e = elements; // status, stage, points, edgeShare, elapsed, remaining, bar, iterations
    this.reset();
    setInterval(() => this.tick(), 1000);
  }

  reset() {
    this.samples = [];
    this.job = null;
    this.edgeShare = null;
  }

  update(job) {
    this.job = job;
    const e = this.e;
    e.status.textContent = job.status;
    e.status.className = `status ${job.status}`;
    const progress = job.progress;
    let stage = progress?.stage || (job.status === 'queued' ? 'waiting for a worker' : '–');
    if (job.status === 'succeeded') stage = 'done';
    else if (FINAL.has(job.status) && progress?.stage) stage = `stopped while ${progress.stage}`;
    e.stage.textContent = stage;
    e.points.textContent = job.points ? formatCount(job.points) : '–';
    // The share is measured by fitting steps only (other stages report 0): keep the last one seen.
    if (progress?.stage === 'fitting' && typeof progress.edge_share === 'number') this.edgeShare = progress.edge_share;
    e.edgeShare.textContent = this.edgeShare === null ? '–' : `${(this.edgeShare * 100).toFixed(1)} %`;
    const total = progress?.total || job.params?.iterations || 1;
    const iteration = job.status === 'succeeded' ? total : (progress?.iteration || 0);
    e.bar.max = total;
    e.bar.value = iteration;
    e.iterations.textContent = `${formatCount(iteration)} / ${formatCount(total)}`;
    if (progress?.stage === 'fitting' && job.status === 'running') {
      const now = performance.now();
      const lastSample = this.samples[this.samples.length - 1];
      if (!lastSample || lastSample[1] !== iteration) this.samples.push([now, iteration]);
      while (this.samples.length > 2 && now - this.samples[0][0] > RATE_WINDOW_MS) this.samples.shift();
    }
    this.tick();
  }

  /** Elapsed time from the job's own timestamps; remaining from the iteration rate seen lately. */
  tick() {
    const job = this.job;
    if (!job) return;
    const e = this.e;
    const started = job.started_at ? Date.parse(job.started_at) : null;
    const ended = job.ended_at ? Date.parse(job.ended_at) : null;
    e.elapsed.textContent = started ? formatSeconds(Math.max(0, ((ended || Date.now()) - started) / 1000)) : '–';
    if (FINAL.has(job.status)) { e.remaining.textContent = job.status === 'succeeded' ? 'done' : '–'; return; }
    if (job.status === 'queued') { e.remaining.textContent = 'not started'; return; }
    const progress = job.progress;
    if (progress?.stage === 'extracting') { e.remaining.textContent = 'extracting the mesh…'; return; }
    let remaining = null;
    if (this.samples.length >= 2) {
      const [t0, i0] = this.samples[0];
      const [t1, i1] = this.samples[this.samples.length - 1];
      // Iterations left at the rate of the last seconds, less the time since the last report.
      if (t1 > t0 && i1 > i0) remaining = (progress.total - i1) / ((i1 - i0) / (t1 - t0)) / 1000 - (performance.now() - t1) / 1000;
    } else if (started && progress?.iteration > 1) {
      const elapsed = Math.max(0.001, (Date.now() - started) / 1000);
      remaining = (progress.total - progress.iteration) * elapsed / progress.iteration;
    }
    e.remaining.textContent = remaining === null ? 'estimating…' : `about ${formatSeconds(Math.max(0, remaining))} of fitting`;
  }
}
