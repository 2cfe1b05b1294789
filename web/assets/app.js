// The labeling page: sign-in, the queue (filters, counts, campaign progress, bulk labels), the
// episode view (synced cameras, plots, metadata, history), keyboard labeling with auto-advance
// and prefetching, and conflict resolution. Plain ES modules, no build step.
//
// The queue is fetched a page at a time as the labeler moves through it (keyset pages of
// /v1/episodes), and the counts and progress bar come from /v1/episodes/counts: the page never
// reads every episode of a campaign, whatever its size.

import * as api from './api.js';
import { Player, prepare, dispose } from './player.js';
import { drawPlots, drawTrajectory } from './plots.js';
import * as consensus from './consensus.js';
import { drawScore } from './review_queue.js';
import { drawTakeovers } from './takeovers.js';
import { $, esc, status } from './dom.js';

const LABELS = ['success', 'failure', 'unknown'];

const S = {
  me: null,
  filters: { policy: '', checkpoint: '', task: '', label: '', order: '' },
  pageSize: 100,    // episodes per page of the queue (`#pagesize=N`)
  queue: [],        // the loaded part of the queue, in order (unknown first by default)
  seen: new Set(),  // ids in `queue`
  pager: null,      // where the next page of the queue comes from
  queueSeq: 0,
  counts: { total: 0, success: 0, failure: 0, unknown: 0 }, // server counts, adjusted locally
  pendingWrites: 0, // label writes in flight (server counts are taken only without any)
  writeGen: 0,
  idx: -1,
  cur: null,        // the prepared episode on screen
  cache: new Map(), // id -> prepared episode (prefetch)
  selected: new Set(),
  plots: null,
  score: null,      // the verifier score plot (review_queue.js)
  takeovers: null,  // the human-takeover strip under the scrub bar (takeovers.js)
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

// ------------------------------------------------------------------ sign-in

async function start() {
  player = new Player({
    grid: $('videos'), scrub: $('scrub'), frameOut: $('frame'), playButton: $('play'),
    onFrame: (f) => { if (S.plots) S.plots.setFrame(f); if (S.score) S.score.setFrame(f); if (S.takeovers) S.takeovers.setFrame(f); if (S.traj) S.traj.setFrame(f); },
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
  consensus.init(S.me);
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
  const n = Number(h.get('pagesize'));
  S.pageSize = Number.isInteger(n) && n >= 1 && n <= 1000 ? n : 100;
}

function writeHash() {
  const h = new URLSearchParams();
  for (const [k, v] of Object.entries(S.filters)) if (v) h.set(k, v);
  if (S.pageSize !== 100) h.set('pagesize', S.pageSize);
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
  $('f-order').value = S.filters.order;
  S.filters.policy = $('f-policy').value;
  S.filters.checkpoint = $('f-checkpoint').value;
  S.filters.task = $('f-task').value;
}

/** Starts the queue over for the current filters: counts, the first page, the episode to show. */
async function loadQueue(focusId) {
  const seq = ++S.queueSeq;
  const { policy, checkpoint, task, label, order } = S.filters;
  S.queue = [];
  S.seen = new Set();
  S.idx = -1;
  S.selected.clear();
  $('queue-list').replaceChildren();
  // "all, unknown first": every unknown episode, then every episode not shown yet.
  S.pager = { base: { policy, checkpoint, task, order }, phases: label ? [label] : ['unknown', ''], phase: 0, after: undefined, done: false, loading: null };
  await Promise.all([refreshCounts(), loadMore()]);
  // An empty first phase (no unknown episode left) moves on to the next one.
  while (!S.queue.length && S.pager && !S.pager.done && seq === S.queueSeq) await loadMore();
  if (seq !== S.queueSeq) return;
  if (focusId && !S.seen.has(focusId)) await addFocus(focusId);
  renderQueue();
  renderCounts();
  let i = focusId ? S.queue.findIndex((e) => e.id === focusId) : -1;
  if (i < 0) i = S.queue.findIndex((e) => e.label === 'unknown');
  if (i < 0) i = S.queue.length ? 0 : -1;
  if (i >= 0) await show(i);
  else showEmpty();
}

/** The episode of the link (`#ep=`), first in the queue when it matches the filters but is not on the first page. */
async function addFocus(id) {
  try {
    const ep = (await api.episode(id)).episode;
    const f = S.filters;
    const matches = ['policy', 'checkpoint', 'task', 'label'].every((k) => !f[k] || ep[k] === f[k]);
    if (matches && !S.seen.has(id)) { S.seen.add(id); S.queue.unshift(ep); }
  } catch { /* not there (any more): start at the first unlabeled one */ }
}

/** Fetches the queue's next page (one at a time); resolves to the number of episodes added. */
function loadMore() {
  const pg = S.pager;
  if (!pg || pg.done) return Promise.resolve(0);
  if (pg.loading) return pg.loading;
  pg.loading = (async () => {
    try {
      const label = pg.phases[pg.phase] || undefined;
      const page = await api.episodesPage({ ...pg.base, label }, pg.after, S.pageSize);
      if (pg !== S.pager) return 0;
      const from = S.queue.length;
      for (const e of page.episodes) {
        if (!S.seen.has(e.id)) { S.seen.add(e.id); S.queue.push(e); }
      }
      if (page.next_cursor) pg.after = page.next_cursor;
      else if (pg.phase + 1 < pg.phases.length) { pg.phase += 1; pg.after = undefined; }
      else pg.done = true;
      appendRows(from);
      return S.queue.length - from;
    } finally {
      pg.loading = null;
    }
  })();
  return pg.loading;
}

/** Keeps a quarter of a page loaded ahead of entry i, so moving on never waits for the server. */
function loadAhead(i) {
  if (S.pager && !S.pager.done && S.queue.length - 1 - i < Math.max(2, S.pageSize >> 2)) {
    loadMore().catch((e) => status($('ep-status'), `cannot load more of the queue: ${e.message}`, 'error'));
  }
}

/** The server's counts for the filters (taken only while none of our writes is in flight). */
async function refreshCounts() {
  const gen = S.writeGen;
  const seq = S.queueSeq;
  try {
    const c = await api.counts(S.pager ? S.pager.base : {});
    if (seq !== S.queueSeq) return;
    if (gen !== S.writeGen || S.pendingWrites > 0) { scheduleCounts(); return; }
    S.counts = c;
    renderCounts();
  } catch { /* keep what is shown; the next write asks again */ }
}

let countsTimer = null;
function scheduleCounts() {
  clearTimeout(countsTimer);
  countsTimer = setTimeout(refreshCounts, 300);
}

/** A label change seen here, reflected in the counts at once (the server's figures follow). */
function countMove(from, to) {
  if (from === to) return;
  if (S.counts[from] !== undefined) S.counts[from] -= 1;
  if (S.counts[to] !== undefined) S.counts[to] += 1;
}

function epName(e) {
  const ix = e.metadata && e.metadata.episode_index !== undefined ? e.metadata.episode_index : e.source_index;
  return `${e.source_name || e.policy} #${ix}`;
}

function rowHtml(e, i) {
  return `<li data-i="${i}" data-id="${esc(e.id)}" class="${i === S.idx ? 'current' : ''}">
      <input type="checkbox" tabindex="-1" ${S.selected.has(e.id) ? 'checked' : ''} aria-label="select">
      <span class="name">${esc(epName(e))}</span>
      <span class="sub">${esc(e.checkpoint)} · ${e.length} steps</span>
      <span class="badge ${esc(e.label)}">${esc(e.label)}</span></li>`;
}

function renderQueue() {
  $('queue-list').innerHTML = S.queue.map(rowHtml).join('');
  $('selected-count').textContent = `${S.selected.size} selected`;
}

/** Adds the rows of queue entries from `from` on (a page just loaded). */
function appendRows(from) {
  const ol = $('queue-list');
  if (ol.children.length !== from) { renderQueue(); return; }
  ol.insertAdjacentHTML('beforeend', S.queue.slice(from).map((e, k) => rowHtml(e, from + k)).join(''));
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
  const c = S.counts;
  const total = c.total;
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

const todo = (i) => S.queue[i].label === 'unknown' && !S.queue[i].pending && !consensus.voted(S.queue[i].id);

/** The next unlabeled entry among those loaded, wrapping around. */
function nextUnlabeled(from) {
  const n = S.queue.length;
  for (let k = 1; k < n; k++) {
    const i = (from + k) % n;
    if (todo(i)) return i;
  }
  return -1;
}

/** The next unlabeled entry after `from`, loading a few more pages if none is loaded; then wraps. */
async function findNextUnlabeled(from) {
  for (let pages = 0; ; pages++) {
    for (let i = from + 1; i < S.queue.length; i++) if (todo(i)) return i;
    if (!S.pager || S.pager.done || pages >= 5) break;
    await loadMore();
  }
  return nextUnlabeled(from);
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
  loadAhead(i);
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
  consensus.show(p.detail.episode);
  if (S.plots) S.plots.destroy();
  if (S.traj) { S.traj.destroy(); S.traj = null; }
  player.attach(p, $('preload'));
  S.plots = drawPlots($('plots'), p.steps, (f) => player.seek(f));
  if (S.score) S.score.destroy();
  S.score = drawScore($('score-plot'), e.id, p.steps.num_rows || 0, (f) => player.seek(f));
  if (S.takeovers) S.takeovers.destroy();
  S.takeovers = drawTakeovers($('takeovers'), $('scrub'), p.steps, p.steps.num_rows || 0, (f) => player.seek(f));
  const traj = $('traj');
  traj.hidden = player.hasVideo(); // image-only episodes (robomimic) keep the sketch under their cameras
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
  status($('ep-status'), ok ? '' : (player.hasCameras() ? 'a camera could not be loaded' : ''), ok ? '' : 'error');
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
  const r = S.queue.find((x) => x.id === ep.id);
  if (r && !r.pending) {
    countMove(r.label, ep.label);
    Object.assign(r, { label: ep.label, label_revision: ep.label_revision, label_actor: ep.label_actor });
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
  if (ep.intervention_steps != null) {
    rows.push(['human takeover', ep.first_intervention == null ? 'none'
      : `from step ${ep.first_intervention} (${ep.intervention_steps} of ${ep.length} steps)`]);
  }
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
  const r = S.queue.find((x) => x.id === id);
  if (r) {
    countMove(r.label, label);
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
  const from = S.idx;
  let next = -1;
  for (let i = from + 1; i < S.queue.length && next < 0; i++) if (todo(i)) next = i;
  if (next >= 0) { show(next, t0); return; }
  // None loaded ahead (the prefetch keeps some): fetch on.
  findNextUnlabeled(from).then((i) => {
    if (S.cur !== p) return;
    if (i >= 0 && i !== S.idx) show(i, t0);
    else {
      renderEpisode(p);
      status($('ep-status'), 'every episode in this queue is labeled', 'ok');
    }
  });
}

async function save(p, label, revision, note, before) {
  const id = p.id;
  S.pendingWrites += 1;
  S.writeGen += 1;
  try {
    const ch = await consensus.save(p.detail.episode, label, revision, note); // a PUT, or a vote
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
  } finally {
    S.pendingWrites -= 1;
    scheduleCounts();
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
    const r = S.queue.find((x) => x.id === id);
    return { episode_id: id, label, expect_revision: r ? r.label_revision : undefined };
  });
  S.pendingWrites += 1;
  S.writeGen += 1;
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
  } finally {
    S.pendingWrites -= 1;
    scheduleCounts();
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
  if (!act) {
    if (consensus.onKey(k, player.frame)) { ev.preventDefault(); metrics.keyActions++; }
    return;
  }
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
  for (const k of ['policy', 'checkpoint', 'task', 'label', 'order']) {
    $(`f-${k}`).addEventListener('change', async (ev) => {
      S.filters[k] = ev.target.value;
      if (k === 'policy') { S.filters.checkpoint = ''; await loadFilters(); }
      await loadQueue(k === 'label' && S.cur ? S.cur.id : undefined);
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
  consensus.wire();
  document.addEventListener('keydown', onKey);
  window.addEventListener('unhandledrejection', (ev) => {
    const e = ev.reason;
    if (e && e.status === 401) showSignIn('your session has ended; sign in again');
    else status($('ep-status'), `error: ${e && e.message ? e.message : e}`, 'error');
  });
}

start();
