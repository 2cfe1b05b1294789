// The episode on screen: prepared (prefetched) episodes and their cache, moving to queue entry i
// (synced cameras, plots, score, steering, takeovers, trajectory) with the time from a verdict key to
// "playable" measured, the next unlabeled entry, and the metadata and label history.

import * as api from './api.js';
import { prepare, dispose } from './player.js';
import { drawPlots, drawTrajectory } from './plots.js';
import * as consensus from './consensus.js';
import { drawScore } from './review_queue.js';
import { drawTakeovers } from './takeovers.js';
import { drawSteering } from './steering.js';
import { $, esc, status } from './dom.js';
import { S, metrics } from './state.js';
import { countMove, epName, loadAhead, loadMore, renderCounts, updateRow, writeHash } from './queue.js';
import { showSignIn } from './signin.js';

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

export const todo = (i) => S.queue[i].label === 'unknown' && !S.queue[i].pending && !consensus.voted(S.queue[i].id);

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
export async function findNextUnlabeled(from) {
  for (let pages = 0; ; pages++) {
    for (let i = from + 1; i < S.queue.length; i++) if (todo(i)) return i;
    if (!S.pager || S.pager.done || pages >= 5) break;
    await loadMore();
  }
  return nextUnlabeled(from);
}

/** Shows queue entry i; `t0` (performance.now() of a verdict key) is measured to "playable". */
export async function show(i, t0) {
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
  S.player.attach(p, $('preload'));
  S.plots = drawPlots($('plots'), p.steps, (f) => S.player.seek(f));
  if (S.score) S.score.destroy();
  S.score = drawScore($('score-plot'), e.id, p.steps.num_rows || 0, (f) => S.player.seek(f));
  if (S.steering) S.steering.destroy();
  S.steering = drawSteering($('steering-plot'), p.steps, (f) => S.player.seek(f));
  if (S.takeovers) S.takeovers.destroy();
  S.takeovers = drawTakeovers($('takeovers'), $('scrub'), p.steps, p.steps.num_rows || 0, (f) => S.player.seek(f));
  const traj = $('traj');
  traj.hidden = S.player.hasVideo(); // image-only episodes (robomimic) keep the sketch under their cameras
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
  status($('ep-status'), ok ? '' : (S.player.hasCameras() ? 'a camera could not be loaded' : ''), ok ? '' : 'error');
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

export async function refreshDetail(p) {
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

export function renderEpisode(p) {
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
