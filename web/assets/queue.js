// The queue beside the episode: filters (kept in the link's `#…`), the episodes fetched a page
// at a time as the labeler moves through it (keyset pages of /v1/episodes), its rows, and the
// counts and progress bar from /v1/episodes/counts: the page never reads every episode of a
// campaign, whatever its size.

import * as api from './api.js';
import { $, esc, status } from './dom.js';
import { LABELS, S, views } from './state.js';
import { notePage, renderReviewNotice, scoreSeen } from './review_queue.js';

export function readHash() {
  const h = new URLSearchParams(location.hash.slice(1));
  for (const k of Object.keys(S.filters)) S.filters[k] = h.get(k) || '';
  S.hashEpisode = h.get('ep') || '';
  const n = Number(h.get('pagesize'));
  S.pageSize = Number.isInteger(n) && n >= 1 && n <= 1000 ? n : 100;
}

export function writeHash() {
  const h = new URLSearchParams();
  for (const [k, v] of Object.entries(S.filters)) if (v) h.set(k, v);
  if (S.pageSize !== 100) h.set('pagesize', S.pageSize);
  if (S.cur) h.set('ep', S.cur.id);
  history.replaceState(null, '', `#${h}`);
}

export async function loadFilters() {
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
export async function loadQueue(focusId) {
  const seq = ++S.queueSeq;
  const { policy, checkpoint, task, label, order } = S.filters;
  S.queue = [];
  S.seen = new Set();
  S.idx = -1;
  S.selected.clear();
  $('queue-list').replaceChildren();
  // "all, unknown first": every unknown episode, then every episode not shown yet.
  S.pager = { base: { policy, checkpoint, task, order }, phases: label ? [label] : ['unknown', ''], phase: 0, after: undefined, done: false, loading: null, scores: scoreSeen() };
  await Promise.all([refreshCounts(), loadMore()]);
  // An empty first phase (no unknown episode left) moves on to the next one.
  while (!S.queue.length && S.pager && !S.pager.done && seq === S.queueSeq) await loadMore();
  if (seq !== S.queueSeq) return;
  showReviewNotice();
  if (focusId && !S.seen.has(focusId)) await addFocus(focusId);
  renderQueue();
  renderCounts();
  let i = focusId ? S.queue.findIndex((e) => e.id === focusId) : -1;
  if (i < 0) i = S.queue.findIndex((e) => e.label === 'unknown');
  if (i < 0) i = S.queue.length ? 0 : -1;
  if (i >= 0) await views.show(i);
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
export function loadMore() {
  const pg = S.pager;
  if (!pg || pg.done) return Promise.resolve(0);
  if (pg.loading) return pg.loading;
  pg.loading = (async () => {
    try {
      const label = pg.phases[pg.phase] || undefined;
      const page = await api.episodesPage({ ...pg.base, label }, pg.after, S.pageSize);
      if (pg !== S.pager) return 0;
      if (page.review) notePage(pg.scores, page);
      const from = S.queue.length;
      for (const e of page.episodes) {
        if (!S.seen.has(e.id)) { S.seen.add(e.id); S.queue.push(e); }
      }
      if (page.next_cursor) pg.after = page.next_cursor;
      else if (pg.phase + 1 < pg.phases.length) { pg.phase += 1; pg.after = undefined; }
      else pg.done = true;
      appendRows(from);
      if (pg.scores.scored && !$('review-notice').hidden) showReviewNotice();
      return S.queue.length - from;
    } finally {
      pg.loading = null;
    }
  })();
  return pg.loading;
}

/** The review orders' word on the queue: unscored episodes come last in them, so a first page
 *  without any score means the order found none to sort by (review_queue.js says what to do). */
function showReviewNotice() {
  const sel = $('f-order');
  const name = sel.selectedOptions[0] ? sel.selectedOptions[0].textContent : S.filters.order;
  renderReviewNotice($('review-notice'), S.filters.order, name, S.pager ? S.pager.scores : scoreSeen());
}

/** Keeps a quarter of a page loaded ahead of entry i, so moving on never waits for the server. */
export function loadAhead(i) {
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

export function scheduleCounts() {
  clearTimeout(S.countsTimer);
  S.countsTimer = setTimeout(refreshCounts, 300);
}

/** A label change seen here, reflected in the counts at once (the server's figures follow). */
export function countMove(from, to) {
  if (from === to) return;
  if (S.counts[from] !== undefined) S.counts[from] -= 1;
  if (S.counts[to] !== undefined) S.counts[to] += 1;
}

export function epName(e) {
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

export function renderQueue() {
  $('queue-list').innerHTML = S.queue.map(rowHtml).join('');
  $('selected-count').textContent = `${S.selected.size} selected`;
}

/** Adds the rows of queue entries from `from` on (a page just loaded). */
function appendRows(from) {
  const ol = $('queue-list');
  if (ol.children.length !== from) { renderQueue(); return; }
  ol.insertAdjacentHTML('beforeend', S.queue.slice(from).map((e, k) => rowHtml(e, from + k)).join(''));
}

export function updateRow(i) {
  const li = $('queue-list').children[i];
  const e = S.queue[i];
  if (!li || !e) return;
  li.className = i === S.idx ? 'current' : '';
  const b = li.querySelector('.badge');
  b.className = `badge ${e.label}`;
  b.textContent = e.label;
  li.querySelector('input').checked = S.selected.has(e.id);
}

export function renderCounts() {
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
