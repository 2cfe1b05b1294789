// Labeling: a verdict on the episode on screen (saved in the background against the revision
// seen, then auto-advance), notes, conflicts (a 409 asks whether to keep theirs or apply mine),
// and the rows selected (x, the boxes) for bulk labels.

import * as api from './api.js';
import * as consensus from './consensus.js';
import { $, esc, status } from './dom.js';
import { S, metrics } from './state.js';
import { countMove, epName, loadQueue, renderCounts, renderQueue, scheduleCounts, updateRow } from './queue.js';
import { findNextUnlabeled, refreshDetail, renderEpisode, show, todo } from './episode.js';

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
export function verdict(label, t0) {
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
  S.player.pause();
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

export async function saveNote() {
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

export async function bulk(label) {
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

export function toggleSelect(i) {
  const e = S.queue[i];
  if (!e) return;
  if (S.selected.has(e.id)) S.selected.delete(e.id); else S.selected.add(e.id);
  updateRow(i);
  $('selected-count').textContent = `${S.selected.size} selected`;
}
