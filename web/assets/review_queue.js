// The review queue's part of the episode view: the verifier's per-step score, as the
// `score` job stored it (GET /v1/episodes/{id}/scores), plotted on the timeline with the same
// frame cursor and click-to-seek as the other plots. The queue-order selector (#f-order) is one
// more filter of app.js: its value goes to GET /v1/episodes as `order`. When an order that needs
// scores finds none, the queue says so and how to get them (#review-notice).

import { call } from './api.js';
import { el } from './dom.js';
import { frameCursor } from './plots.js';

/** The orders that sort by a stored verifier score (unscored episodes come last in them). */
export const SCORED_ORDERS = new Set(['uncertain', 'disagreement']);

/** What the loaded pages of a queue say about its scores: whether any episode has one, and
 *  per policy/checkpoint whether a review artifact would score it. Fed each page's `review`. */
export function scoreSeen() {
  return { scored: false, pairs: new Map() };
}

/** Adds a page of GET /v1/episodes?order=… (its `episodes` and their `review` entries). */
export function notePage(seen, page) {
  const byId = new Map((page.review || []).map((r) => [r.episode_id, r]));
  for (const e of page.episodes) {
    const r = byId.get(e.id);
    if (!r) continue;
    if (r.score !== null && r.score !== undefined) seen.scored = true;
    const key = `${e.policy}\u0000${e.checkpoint}`;
    const p = seen.pairs.get(key) || { policy: e.policy, checkpoint: e.checkpoint, artifact: null };
    if (r.artifact_id) p.artifact = r.artifact_id;
    seen.pairs.set(key, p);
  }
}

/** Shows in `box` why a score order lists the episodes by id, and the commands that store the
 *  scores (a score job per policy/checkpoint, or first a classifier where none would score);
 *  hides it when the order needs no scores, the queue is empty or some episode is scored. */
export function renderReviewNotice(box, order, orderName, seen) {
  box.replaceChildren();
  const pairs = [...seen.pairs.values()];
  if (!SCORED_ORDERS.has(order) || seen.scored || pairs.length === 0) {
    box.hidden = true;
    delete box.dataset.state;
    return;
  }
  const withArt = pairs.filter((p) => p.artifact);
  const without = pairs.filter((p) => !p.artifact);
  box.dataset.state = withArt.length ? 'unscored' : 'no-verifier';
  box.appendChild(el('strong', {}, 'No verifier scores yet'));
  box.appendChild(el('p', {}, `“${orderName}” sorts by the score a verifier gave each episode; none of these has one, ` +
    'so they are listed by id.'));
  // One flag pair a line (shell continuations), so a narrow queue never splits a flag.
  const pre = (lines) => el('pre', {}, lines.join('\n'));
  const score = (p) => `ufops review score \\\n  --policy ${p.policy} --checkpoint ${p.checkpoint}`;
  if (withArt.length) {
    box.appendChild(el('p', {}, 'A score job stores them. A trainer runs, on the server\'s store:'));
    const more = withArt.length > 3 ? [`# … and ${withArt.length - 3} more checkpoints`] : [];
    box.appendChild(pre([...withArt.slice(0, 3).map(score), ...more]));
    const p0 = withArt[0];
    box.appendChild(el('p', {}, `or POSTs {"policy": "${p0.policy}", "checkpoint": "${p0.checkpoint}"} to ` +
      '/v1/review/score. Reload this page when the job has finished.'));
  }
  if (without.length) {
    const names = without.map((p) => `${p.policy}/${p.checkpoint}`);
    const p0 = without[0];
    box.appendChild(el('p', {}, `${names.slice(0, 3).join(', ')}${names.length > 3 ? ' …' : ''} ` +
      `${names.length === 1 ? 'has' : 'have'} no verifier to score with. A trainer first trains a classifier ` +
      'on labeled episodes (H: the policy\'s action chunk length; it becomes classifier@latest), then scores:'));
    box.appendChild(pre([
      `ufops split create \\\n  --policy ${p0.policy} --checkpoint ${p0.checkpoint}`,
      'ufops train --split SPLIT_ID \\\n  --kind classifier --chunk-len H',
      score(p0),
    ]));
  }
  box.hidden = false;
}

/** The stored per-step scores of an episode, or null when it has none (404: not scored yet). */
export async function episodeScores(id) {
  try {
    return await call('GET', `/v1/episodes/${encodeURIComponent(id)}/scores`);
  } catch (e) {
    if (e.status === 404) return null;
    throw e;
  }
}

/** Draws the score of episode `id` (n frames) into `el` once fetched (never delays the video);
 *  returns {setFrame, destroy} like drawPlots. Shows nothing for an unscored episode. */
export function drawScore(el, id, n, onSeek) {
  el.replaceChildren();
  el.hidden = true;
  let u = null;
  let line = null;
  let frame = 0;
  let gone = false;
  episodeScores(id).then((s) => {
    if (gone || !s || !Array.isArray(s.step_scores) || s.step_scores.length === 0) return;
    el.hidden = false;
    const ys = s.step_scores;
    const xs = Array.from({ length: ys.length }, (_, i) => i);
    const half = xs.map(() => 0.5);
    const box = document.createElement('div');
    box.className = 'plot';
    el.appendChild(box);
    const opts = {
      title: `verifier score (mean ${s.score.toFixed(3)}, ${s.artifact_id})`,
      width: Math.max(320, el.clientWidth - 8), height: 150,
      series: [{ label: 'frame' }, { label: 'score', stroke: '#d62728', width: 2 },
        { label: '0.5', stroke: '#999', width: 1, dash: [4, 4] }],
      scales: { x: { time: false }, y: { range: [0, 1] } },
      axes: [{ size: 28 }, { size: 48 }],
      cursor: { drag: { x: false, y: false }, points: { show: false } },
    };
    // eslint-disable-next-line no-undef
    u = new uPlot(opts, [xs, ys, half], box);
    line = frameCursor(u, n, onSeek);
    line.style.left = `${u.valToPos(frame, 'x')}px`;
    el.dataset.scored = id;
  }).catch(() => { /* the timeline works without the score */ });
  return {
    setFrame(t) {
      frame = t;
      if (u && line) line.style.left = `${u.valToPos(t, 'x')}px`;
    },
    destroy() {
      gone = true;
      if (u) u.destroy();
      el.replaceChildren();
      delete el.dataset.scored;
    },
  };
}
