// The review queue's part of the episode view: the verifier's per-step score, as the
// `score` job stored it (GET /v1/episodes/{id}/scores), plotted on the timeline with the same
// frame cursor and click-to-seek as the other plots. The queue-order selector (#f-order) is one
// more filter of app.js: its value goes to GET /v1/episodes as `order`.

import { call } from './api.js';
import { frameCursor } from './plots.js';

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
