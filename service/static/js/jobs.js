// The jobs this browser submitted (local storage: id, file name, time), with their status;
// any of them can be reopened.

import {ApiError, FINAL, getJob} from './api.js';
import {el} from './ui.js';

const STORAGE = 'edgerecon.jobs';
const KEEP = 50; // most recent jobs remembered
const REFRESH_MS = 5000; // while a listed job is queued or running

export class JobList {
  constructor(list, onOpen) {
    this.list = list;
    this.onOpen = onOpen;
    this.statuses = new Map(); // id -> status text
    this.current = null;
    this.timer = null;
  }

  entries() {
    try {
      const entries = JSON.parse(localStorage.getItem(STORAGE) || '[]');
      return Array.isArray(entries) ? entries.filter((entry) => entry && typeof entry.id === 'string') : [];
    } catch {
      return [];
    }
  }

  save(entries) {
    localStorage.setItem(STORAGE, JSON.stringify(entries.slice(0, KEEP)));
  }

  add(job, fileName) {
    const entries = this.entries().filter((entry) => entry.id !== job.id);
    entries.unshift({id: job.id, name: fileName, time: new Date().toISOString()});
    this.save(entries);
    this.statuses.set(job.id, job.status);
    this.render();
  }

  forget(id) {
    this.save(this.entries().filter((entry) => entry.id !== id));
    this.statuses.delete(id);
    this.render();
  }

  /** A job's status as the page last saw it (from a watch or a refresh). */
  update(job) {
    if (this.statuses.get(job.id) === job.status) return;
    this.statuses.set(job.id, job.status);
    this.render();
  }

  setCurrent(id) {
    this.current = id;
    this.render();
  }

  /** Ask the service for the status of every listed job that is not known to be final. */
  async refresh(all = false) {
    clearTimeout(this.timer);
    for (const entry of this.entries()) {
      const known = this.statuses.get(entry.id);
      if (!all && known && (FINAL.has(known) || known === 'expired')) continue;
      try {
        this.statuses.set(entry.id, (await getJob(entry.id)).status);
      } catch (error) {
        if (!(error instanceof ApiError)) throw error;
        if (error.status === 404) this.statuses.set(entry.id, 'expired');
        else this.statuses.set(entry.id, error.status === 401 ? 'unknown (API key?)' : 'unknown (no answer)');
        if (error.status === 401 || error.status === 0) break;
      }
    }
    this.render();
    if (this.entries().some((entry) => ['queued', 'running'].includes(this.statuses.get(entry.id)))) {
      this.timer = setTimeout(() => this.refresh(), REFRESH_MS);
    }
  }

  render() {
    const entries = this.entries();
    if (!entries.length) {
      this.list.replaceChildren(el('li', {class: 'hint'}, 'None yet.'));
      return;
    }
    this.list.replaceChildren(...entries.map((entry) => {
      const status = this.statuses.get(entry.id) || '…';
      const when = new Date(entry.time);
      return el('li', {class: entry.id === this.current ? 'current' : null, 'data-job': entry.id},
        el('span', {class: 'name'}, entry.name || '(no name)'),
        el('span', {class: `status ${status.split(' ')[0]}`}, status),
        el('span', {class: 'meta'}, `${isNaN(when) ? '' : when.toLocaleString()} · `, el('code', {}, entry.id)),
        el('span', {class: 'actions'},
          el('button', {type: 'button', 'aria-label': `Open job ${entry.id}`, onclick: () => this.onOpen(entry.id, entry.name)}, 'Open'),
          el('button', {type: 'button', 'aria-label': `Forget job ${entry.id}`, onclick: () => this.forget(entry.id)}, 'Forget')));
    }));
  }
}
