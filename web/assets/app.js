// The labeling page: sign-in, the queue (filters, counts, campaign progress, bulk labels), the
// episode view (synced cameras, plots, metadata, history), keyboard labeling with auto-advance
// and prefetching, and conflict resolution. Plain ES modules, no build step.

import * as api from './api.js';
import { Player, prepare, dispose } from './player.js';
import { drawPlots, drawTrajectory } from './plots.js';

const $ = (id) => document.getElementById(id);
const LABELS = ['success', 'failure', 'unknown'];

const S = {
  me: null,
  filters: { policy: '', checkpoint: '', task: '', label: '' },
  all: [],          // episodes matching policy/checkpoint/task (for counts)
  queue: [],        // the shown order (label filter applied; unknown first by default)
  idx: -1,
  cur: null,        // the prepared episode on screen
  cache: new Map(), // id -> prepared episode (prefetch)
  selected: new Set(),
  plots: null,
  traj: null,
  showSeq: 0,
  conflicts: [],    // pending conflicts to ask about
  conflictOpen: false,
};

// Measurements the end-to-end test reads (and the page shows): keyboard actions, and the time
// from a verdict key to the next episode being playable.
const metrics = { keyActions: 0, verdicts: 0, advances: [] };
window.ufops = { metrics, state: S };

let player;

function esc(s) {
  return String(s ?? '').replace(/[&<>"']/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;' }[c]));
}

function status(el, text, kind) {
  el.textContent = text || '';
  el.className = `status ${kind || ''}`;
}

// ------------------------------------------------------------------ sign-in

async function start() {
  player = new Player({
    grid: $('videos'), scrub: $('scrub'), frameOut: $('frame'), playButton: $('play'),
    onFrame: (f) => { if (S.plots) S.plots.setFrame(f); if (S.traj) S.traj.setFrame(f); },
  });
  wire();
  try {
    S.me = await api.session();
    await enter();
  } catch (e) {
    showSignIn(e.status === 401 ? '' : e.message);
  }
}

function showSignIn(msg) {
  $('app').hidden = true;
  $('signin').hidden = false;
  $('signin-error').textContent = msg || '';
  $('token').value = '';
  $('token').focus();
}

async function enter() {
  $('signin').hidden = true;
  $('app').hidden = false;
  $('me').textContent = `${S.me.name} (${S.me.role})`;
  if (document.activeElement && document.activeElement !== document.body) document.activeElement.blur();
  readHash();
  await loadFilters();
  await loadQueue(S.hashEpisode);
}

// ------------------------------------------------------------------ queue

function readHash() {
  const h = new URLSearchParams(location.hash.slice(1));
  for (const k of Object.keys(S.filters)) S.filters[k] = h.get(k) || '';
  S.hashEpisode = h.get('ep') || '';
}

function writeHash() {
  const h = new URLSearchParams();
  for (const [k, v] of Object.entries(S.filters)) if (v) h.set(k, v);
  if (S.cur) h.set('ep', S.cur.id);
  history.replaceState(null, '', `#${h}`);
}

async function loadFilters() {
  const fill = (sel, values, current) => {
    sel.replaceChildren(new Option('all', ''));
    for (const v of values) sel.appendChild(new Option(v, v));
    sel.value = values.includes(current) ? current : '';
  };
  const [pols, cks, tks] = await Promise.all([api.policies(), api.checkpoints(S.filters.policy || undefined), api.tasks()]);
  fill($('f-policy'), pols, S.filters.policy);
  fill($('f-checkpoint'), [...new Set(cks.map((c) => c.checkpoint))], S.filters.checkpoint);
  fill($('f-task'), tks, S.filters.task);
  $('f-label').value = S.filters.label;
  S.filters.policy = $('f-policy').value;
  S.filters.checkpoint = $('f-checkpoint').value;
  S.filters.task = $('f-task').value;
}

async function loadQueue(focusId) {
  const { policy, checkpoint, task } = S.filters;
  S.all = await api.allEpisodes({ policy, checkpoint, task });
  orderQueue();
  S.selected.clear();
  renderQueue();
  renderCounts();
  let i = focusId ? S.queue.findIndex((e) => e.id === focusId) : -1;
  if (i < 0) i = S.queue.findIndex((e) => e.label === 'unknown');
  if (i < 0) i = S.queue.length ? 0 : -1;
  if (i >= 0) await show(i);
  else showEmpty();
}

function orderQueue() {
  const want = S.filters.label;
  const list = want ? S.all.filter((e) => e.label === want) : [...S.all];
  if (!want) list.sort((a, b) => (a.label === 'unknown' ? 0 : 1) - (b.label === 'unknown' ? 0 : 1) || (a.id < b.id ? -1 : a.id > b.id ? 1 : 0));
  S.queue = list;
}

function epName(e) {
  const ix = e.metadata && e.metadata.episode_index !== undefined ? e.metadata.episode_index : e.source_index;
  return `${e.source_name || e.policy} #${ix}`;
}

function renderQueue() {
  const ol = $('queue-list');
  const rows = S.queue.map((e, i) => `<li data-i="${i}" data-id="${esc(e.id)}" class="${i === S.idx ? 'current' : ''}">
      <input type="checkbox" tabindex="-1" ${S.selected.has(e.id) ? 'checked' : ''} aria-label="select">
      <span class="name">${esc(epName(e))}</span>
      <span class="sub">${esc(e.checkpoint)} · ${e.length} steps</span>
      <span class="badge ${esc(e.label)}">${esc(e.label)}</span></li>`);
  ol.innerHTML = rows.join('');
  $('selected-count').textContent = `${S.selected.size} selected`;
}

function updateRow(i) {
  const li = $('queue-list').children[i];
  const e = S.queue[i];
  if (!li || !e) return;
  li.className = i === S.idx ? 'current' : '';
  const b = li.querySelector('.badge');
  b.className = `badge ${e.label}`;
  b.textContent = e.label;
  li.querySelector('input').checked = S.selected.has(e.id);
}

function renderCounts() {
  const c = { success: 0, failure: 0, unknown: 0 };
  for (const e of S.all) c[e.label] = (c[e.label] || 0) + 1;
  const total = S.all.length;
  const done = c.success + c.failure;
  $('counts').innerHTML = LABELS.map((l) => `<span class="badge ${l}" data-count="${l}">${l} ${c[l]}</span>`).join(' ');
  $('progress-fill').style.width = total ? `${(100 * done) / total}%` : '0';
  $('progress-text').textContent = `${done} / ${total} labeled`;
}

function showEmpty() {
  S.cur = null;
  $('ep-title').textContent = 'No episodes match these filters';
  $('videos').replaceChildren();
  $('plots').replaceChildren();
}

// ------------------------------------------------------------------ episode view

function prepared(id) {
  let p = S.cache.get(id);
  if (!p) {
    p = prepare(id, $('preload'));
    S.cache.set(id, p);
  }
  return p;
}

function trimCache(keep) {
  for (const [id, p] of S.cache) {
    if (!keep.has(id)) { dispose(p); S.cache.delete(id); }
  }
}

function nextUnlabeled(from) {
  const n = S.queue.length;
  for (let k = 1; k < n; k++) {
    const i = (from + k) % n;
    if (S.queue[i].label === 'unknown' && !S.queue[i].pending) return i;
  }
  return -1;
}

/** Shows queue entry i; `t0` (performance.now() of a verdict key) is measured to "playable". */
async function show(i, t0) {
  if (i < 0 || i >= S.queue.length) return;
  const seq = ++S.showSeq;
  const prev = S.idx;
  S.idx = i;
  updateRow(prev);
  updateRow(i);
  const li = $('queue-list').children[i];
  if (li) li.scrollIntoView({ block: 'nearest' });
  const e = S.queue[i];
  const p = prepared(e.id);
  document.body.dataset.ready = '';
  status($('ep-status'), 'loading…');
  await p.loaded;
  if (seq !== S.showSeq) return;
  if (p.error) {
    S.cache.delete(e.id); // try again next time
    if (p.error.status === 401) { showSignIn('your session has ended; sign in again'); return; }
    status($('ep-status'), `cannot load ${e.id}: ${p.error.message}`, 'error');
    return;
  }
  S.cur = p;
  writeHash();
  renderEpisode(p);
  if (S.plots) S.plots.destroy();
  if (S.traj) { S.traj.destroy(); S.traj = null; }
  player.attach(p, $('preload'));
  S.plots = drawPlots($('plots'), p.steps, (f) => player.seek(f));
  const traj = $('traj');
  traj.hidden = p.cams.length > 0;
  if (!traj.hidden) S.traj = drawTrajectory(traj, p.steps);
  S.plots.setFrame(0);
  const ok = await p.ready;
  if (seq !== S.showSeq) return;
  const ms = t0 !== undefined ? performance.now() - t0 : null;
  if (ms !== null) {
    metrics.advances.push({ to: e.id, ms, videos: p.cams.length, playable: ok });
    const v = metrics.advances.map((a) => a.ms).sort((a, b) => a - b);
    $('speed').textContent = `verdict → next episode playable: median ${v[v.length >> 1].toFixed(0)} ms, max ${v[v.length - 1].toFixed(0)} ms (${v.length})`;
  }
  status($('ep-status'), ok ? '' : (p.cams.length ? 'video not playable in this browser' : ''), ok ? '' : 'error');
  document.body.dataset.ready = e.id;
  // Prefetch: the next unlabeled episode (where a verdict goes) and the neighbours (j / k).
  const keep = new Set([e.id]);
  for (const j of [nextUnlabeled(i), i + 1, i - 1]) {
    if (j >= 0 && j < S.queue.length) { keep.add(S.queue[j].id); prepared(S.queue[j].id); }
  }
  trimCache(keep);
  // Refresh what the prefetch may have read a while ago (label, revision, history).
  if (t0 === undefined || Date.now() - (p.fetchedAt || 0) > 5000) refreshDetail(p);
}

async function refreshDetail(p) {
  try {
    const d = await api.episode(p.id);
    p.detail = d;
    p.fetchedAt = Date.now();
    syncRecord(d.episode);
    if (S.cur === p) renderEpisode(p);
  } catch { /* keep the older copy */ }
}

function syncRecord(ep) {
  for (const list of [S.all, S.queue]) {
    const r = list.find((x) => x.id === ep.id);
    if (r && !r.pending) Object.assign(r, { label: ep.label, label_revision: ep.label_revision, label_actor: ep.label_actor });
  }
  const i = S.queue.findIndex((x) => x.id === ep.id);
  if (i >= 0) updateRow(i);
  renderCounts();
}

function renderEpisode(p) {
  const ep = p.detail.episode;
  $('ep-title').textContent = `${epName(ep)} — ${ep.policy} / ${ep.checkpoint}${ep.task ? ` — ${ep.task}` : ''}`;
  const rec = S.queue.find((x) => x.id === ep.id);
  const label = rec && rec.pending ? rec.label : ep.label;
  $('ep-label').className = `badge ${label}`;
  $('ep-label').textContent = label + (rec && rec.pending ? ' (saving)' : '');
  document.body.dataset.episode = ep.id;
  const rows = [
    ['id', ep.id], ['policy', ep.policy], ['checkpoint', ep.checkpoint], ['task', ep.task || '—'],
    ['steps', ep.length], ['source', `${ep.source_name} [${ep.source_index}]`], ['version added', ep.version_added],
    ['label', `${ep.label} (rev ${ep.label_revision}${ep.label_actor ? `, ${ep.label_actor}` : ''}${ep.label_source ? `, ${ep.label_source}` : ''})`],
    ['tags', (ep.tags || []).join(', ') || '—'],
  ];
  const md = ep.metadata || {};
  for (const [k, v] of Object.entries(md)) {
    if (k === 'videos' && v && typeof v === 'object') {
      for (const [vk, vv] of Object.entries(v)) rows.push([`video ${vk}`, `${vv.file || ''} from ${Number(vv.from_timestamp || 0).toFixed(3)} s`]);
    } else rows.push([k, typeof v === 'object' ? JSON.stringify(v) : v]);
  }
  $('meta').innerHTML = rows.map(([k, v]) => `<tr><th>${esc(k)}</th><td>${esc(v)}</td></tr>`).join('');
  const hist = [...(p.detail.history || [])].reverse();
  $('history').innerHTML = hist.length
    ? hist.map((h) => `<li><span class="badge ${esc(h.new_label)}">${esc(h.new_label)}</span> by <b>${esc(h.actor)}</b>
        <span class="sub">${esc(h.source)} · rev ${h.revision} · ${esc(h.created_at)}</span>${h.note ? `<div class="note">${esc(h.note)}</div>` : ''}</li>`).join('')
    : '<li class="sub">no label events yet</li>';
}

// ------------------------------------------------------------------ labeling

function setLocal(id, label, revision, actor, pending) {
  for (const list of [S.all, S.queue]) {
    const r = list.find((x) => x.id === id);
    if (!r) continue;
    r.label = label;
    if (revision !== undefined) r.label_revision = revision;
    if (actor !== undefined) r.label_actor = actor;
    r.pending = pending;
  }
  const i = S.queue.findIndex((x) => x.id === id);
  if (i >= 0) updateRow(i);
  renderCounts();
}

/** A verdict on the episode on screen: saved against the revision seen, then auto-advance. */
function verdict(label, t0) {
  const p = S.cur;
  if (!p || S.conflictOpen) return;
  const ep = p.detail.episode;
  const rec = S.queue.find((x) => x.id === ep.id);
  const before = { label: rec ? rec.label : ep.label };
  const note = $('note').value.trim();
  $('note').value = '';
  metrics.verdicts++;
  const revision = ep.label_revision;
  setLocal(ep.id, label, undefined, undefined, true);
  save(p, label, revision, note, before);
  const next = nextUnlabeled(S.idx);
  if (next >= 0) show(next, t0);
  else {
    renderEpisode(p);
    status($('ep-status'), 'every episode in this queue is labeled', 'ok');
  }
}

async function save(p, label, revision, note, before) {
  const id = p.id;
  try {
    const ch = await api.putLabel(id, label, revision, note);
    setLocal(id, ch.label, ch.revision, ch.actor, false);
    p.detail.episode = { ...p.detail.episode, label: ch.label, label_revision: ch.revision, label_actor: ch.actor };
    refreshDetail(p);
  } catch (e) {
    if (e.status === 409 && e.problem.current_revision !== undefined) {
      const pr = e.problem;
      setLocal(id, pr.current_label, pr.current_revision, pr.set_by, false);
      p.detail.episode = { ...p.detail.episode, label: pr.current_label, label_revision: pr.current_revision, label_actor: pr.set_by };
      S.conflicts.push({ p, label, note, problem: pr });
      askConflict();
      refreshDetail(p);
    } else {
      setLocal(id, before.label, undefined, undefined, false);
      status($('ep-status'), `label of ${id} not saved: ${e.message}`, 'error');
    }
  }
}

async function askConflict() {
  if (S.conflictOpen || !S.conflicts.length) return;
  const c = S.conflicts.shift();
  S.conflictOpen = true;
  player.pause();
  const pr = c.problem;
  const rec = S.queue.find((x) => x.id === c.p.id) || c.p.detail.episode;
  $('conflict-text').innerHTML = `<b>${esc(epName(rec))}</b> was changed by <b class="who">${esc(pr.set_by)}</b>
    at ${esc(pr.set_at)}: it is now <span class="badge ${esc(pr.current_label)}">${esc(pr.current_label)}</span>
    (revision ${pr.current_revision}). You chose <span class="badge ${esc(c.label)}">${esc(c.label)}</span>
    against revision ${pr.expected_revision}. Nothing was overwritten.`;
  $('conflict-mine').textContent = `Apply mine (${c.label})`;
  document.body.dataset.conflict = c.p.id;
  const dlg = $('conflict');
  dlg.returnValue = '';
  dlg.showModal();
  $('conflict-keep').focus();
  const choice = await new Promise((resolve) => dlg.addEventListener('close', () => resolve(dlg.returnValue), { once: true }));
  S.conflictOpen = false;
  document.body.dataset.conflict = '';
  if (choice === 'mine') {
    setLocal(c.p.id, c.label, undefined, undefined, true);
    await save(c.p, c.label, pr.current_revision, c.note, { label: pr.current_label });
    status($('ep-status'), `applied ${c.label} to ${epName(rec)} over ${pr.set_by}'s ${pr.current_label}`, 'ok');
  } else {
    status($('ep-status'), `kept ${pr.set_by}'s ${pr.current_label} on ${epName(rec)}`, 'ok');
  }
  if (S.cur === c.p) renderEpisode(c.p);
  askConflict();
}

async function saveNote() {
  const p = S.cur;
  const note = $('note').value.trim();
  $('note').blur();
  if (!p || !note) return;
  $('note').value = '';
  const rec = S.queue.find((x) => x.id === p.id);
  const label = rec ? rec.label : p.detail.episode.label;
  await save(p, label, p.detail.episode.label_revision, note, { label });
  status($('ep-status'), 'note saved', 'ok');
}

async function bulk(label) {
  const ids = [...S.selected];
  if (!ids.length) { status($('bulk-status'), 'select episodes first (click the boxes or press x)', 'error'); return; }
  const updates = ids.map((id) => {
    const r = S.all.find((x) => x.id === id);
    return { episode_id: id, label, expect_revision: r ? r.label_revision : undefined };
  });
  try {
    const changes = await api.bulkLabel(updates);
    for (const ch of changes) setLocal(ch.episode_id, ch.label, ch.revision, ch.actor, false);
    S.selected.clear();
    renderQueue();
    status($('bulk-status'), `${changes.length} episodes labeled ${label}`, 'ok');
    if (S.cur) refreshDetail(S.cur);
  } catch (e) {
    const pr = e.problem || {};
    const who = pr.set_by ? ` (${pr.episode_id} is now ${pr.current_label}, set by ${pr.set_by}); nothing was changed — the list is reloaded` : '';
    status($('bulk-status'), `bulk label refused: ${e.message}${who}`, 'error');
    if (e.status === 409) await loadQueue(S.cur && S.cur.id);
  }
}

function toggleSelect(i) {
  const e = S.queue[i];
  if (!e) return;
  if (S.selected.has(e.id)) S.selected.delete(e.id); else S.selected.add(e.id);
  updateRow(i);
  $('selected-count').textContent = `${S.selected.size} selected`;
}

// ------------------------------------------------------------------ wiring

function onKey(ev) {
  if (ev.ctrlKey || ev.metaKey || ev.altKey || $('app').hidden || S.conflictOpen) return;
  const t = ev.target;
  if (t && (t.tagName === 'INPUT' || t.tagName === 'SELECT' || t.tagName === 'TEXTAREA') && t.type !== 'checkbox' && t.type !== 'range') {
    if (t.id === 'note' && ev.key === 'Enter') { ev.preventDefault(); saveNote(); }
    if (ev.key === 'Escape') t.blur();
    return;
  }
  const k = ev.key;
  if (t && t.tagName === 'BUTTON') t.blur(); // space/Enter must not also press a focused button
  const act = {
    s: () => verdict('success', ev.timeStamp),
    f: () => verdict('failure', ev.timeStamp),
    u: () => verdict('unknown', ev.timeStamp),
    n: () => $('note').focus(),
    j: () => show(Math.min(S.queue.length - 1, S.idx + 1)),
    k: () => show(Math.max(0, S.idx - 1)),
    ' ': () => player.toggle(),
    ',': () => { player.pause(); player.step(-1); },
    '.': () => { player.pause(); player.step(1); },
    x: () => toggleSelect(S.idx),
  }[k];
  if (!act) return;
  ev.preventDefault();
  metrics.keyActions++;
  act();
}

function wire() {
  $('signin-form').addEventListener('submit', async (ev) => {
    ev.preventDefault();
    $('signin-error').textContent = '';
    try {
      S.me = await api.signIn($('token').value);
      $('token').value = '';
      await enter();
    } catch (e) {
      showSignIn(e.status === 401 ? 'unknown or revoked token' : e.message);
    }
  });
  $('signout').addEventListener('click', async () => {
    try { await api.signOut(); } catch { /* the cookie is cleared either way */ }
    player.pause();
    showSignIn('signed out');
  });
  for (const k of ['policy', 'checkpoint', 'task', 'label']) {
    $(`f-${k}`).addEventListener('change', async (ev) => {
      S.filters[k] = ev.target.value;
      if (k === 'policy') { S.filters.checkpoint = ''; await loadFilters(); }
      if (k === 'label') { orderQueue(); renderQueue(); const i = S.queue.findIndex((e) => S.cur && e.id === S.cur.id); S.idx = -1; await show(i >= 0 ? i : 0); return; }
      await loadQueue();
    });
  }
  $('queue-list').addEventListener('click', (ev) => {
    const li = ev.target.closest('li');
    if (!li) return;
    const i = Number(li.dataset.i);
    if (ev.target.tagName === 'INPUT') { toggleSelect(i); return; }
    show(i);
  });
  $('select-all').addEventListener('change', (ev) => {
    S.selected = new Set(ev.target.checked ? S.queue.map((e) => e.id) : []);
    renderQueue();
  });
  for (const b of document.querySelectorAll('[data-bulk]')) b.addEventListener('click', () => bulk(b.dataset.bulk));
  for (const b of document.querySelectorAll('[data-label]')) b.addEventListener('click', () => verdict(b.dataset.label, performance.now()));
  $('play').addEventListener('click', () => player.toggle());
  $('prev-frame').addEventListener('click', () => player.step(-1));
  $('next-frame').addEventListener('click', () => player.step(1));
  document.addEventListener('keydown', onKey);
  window.addEventListener('unhandledrejection', (ev) => {
    const e = ev.reason;
    if (e && e.status === 401) showSignIn('your session has ended; sign in again');
    else status($('ep-status'), `error: ${e && e.message ? e.message : e}`, 'error');
  });
}

start();
