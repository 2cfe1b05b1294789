// The page's wiring: the keyboard map (verdicts, notes, moving through the queue, playback,
// selection; the consensus panel's keys) and every control's event handler.

import * as api from './api.js';
import * as consensus from './consensus.js';
import { $, status } from './dom.js';
import { S, metrics } from './state.js';
import { loadFilters, loadQueue, renderQueue } from './queue.js';
import { show } from './episode.js';
import { bulk, saveNote, toggleSelect, verdict } from './labeling.js';
import { enter, showSignIn } from './signin.js';

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
    ' ': () => S.player.toggle(),
    ',': () => { S.player.pause(); S.player.step(-1); },
    '.': () => { S.player.pause(); S.player.step(1); },
    x: () => toggleSelect(S.idx),
  }[k];
  if (!act) {
    if (consensus.onKey(k, S.player.frame)) { ev.preventDefault(); metrics.keyActions++; }
    return;
  }
  ev.preventDefault();
  metrics.keyActions++;
  act();
}

export function wire() {
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
    S.player.pause();
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
  $('play').addEventListener('click', () => S.player.toggle());
  $('prev-frame').addEventListener('click', () => S.player.step(-1));
  $('next-frame').addEventListener('click', () => S.player.step(1));
  consensus.wire();
  document.addEventListener('keydown', onKey);
  window.addEventListener('unhandledrejection', (ev) => {
    const e = ev.reason;
    if (e && e.status === 401) showSignIn('your session has ended; sign in again');
    else status($('ep-status'), `error: ${e && e.message ? e.message : e}`, 'error');
  });
}
