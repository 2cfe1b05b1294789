// The steering timeline of a steered episode: at each best-of-N step (the steps' `steering`
// column), the spread of the candidates' scores (lowest to highest, shaded), their median, and
// the score of the candidate the robot executed; a click seeks to that frame.

import { frameCursor } from './plots.js';

/** The best-of-N records of a steps document, `[{t, n, lo, median, hi, chosen, artifact, latency}]`. */
export function steeringSteps(steps) {
  const col = (steps.columns || {}).steering;
  if (!Array.isArray(col)) return [];
  const out = [];
  col.forEach((r, t) => {
    if (!r || !Array.isArray(r.scores) || r.scores.length === 0) return;
    const s = [...r.scores].sort((a, b) => a - b);
    out.push({
      t, n: s.length, lo: s[0], hi: s[s.length - 1], median: s[s.length >> 1],
      chosen: r.scores[r.chosen], artifact: r.artifact_id, latency: r.latency_us,
    });
  });
  return out;
}

/** Draws the steering timeline into `el` (hidden for an unsteered episode). */
export function drawSteering(el, steps, onSeek) {
  el.replaceChildren();
  const recs = steeringSteps(steps);
  el.hidden = recs.length === 0;
  if (!recs.length) return { setFrame() {}, destroy() {} };
  const n = steps.num_rows || 0;
  const xs = Array.from({ length: n }, (_, i) => i);
  const at = (f) => { const y = xs.map(() => null); for (const r of recs) y[r.t] = f(r); return y; };
  const lat = recs.map((r) => r.latency).sort((a, b) => a - b);
  const ns = [...new Set(recs.map((r) => r.n))].join(', ');
  const artifacts = [...new Set(recs.map((r) => r.artifact))].join(', ');
  const box = document.createElement('div');
  box.className = 'plot';
  el.appendChild(box);
  const pts = (color) => ({ show: true, size: 6, stroke: color, fill: color });
  const opts = {
    title: `best-of-N: ${recs.length} steps, N = ${ns}, verifier ${artifacts}, scoring median ${lat[lat.length >> 1]} µs`,
    width: Math.max(320, el.clientWidth - 8), height: 150,
    series: [
      { label: 'frame' },
      { label: 'lowest', stroke: '#9ecae1', width: 1, points: pts('#9ecae1'), spanGaps: true },
      { label: 'highest', stroke: '#9ecae1', width: 1, points: pts('#9ecae1'), spanGaps: true },
      { label: 'median', stroke: '#888', width: 1, dash: [4, 4], points: pts('#888'), spanGaps: true },
      { label: 'chosen', stroke: '#d62728', width: 2, points: pts('#d62728'), spanGaps: true },
    ],
    bands: [{ series: [2, 1], fill: 'rgba(158, 202, 225, 0.35)' }],
    scales: { x: { time: false, range: [0, Math.max(1, n - 1)] } },
    axes: [{ size: 28 }, { size: 48 }],
    cursor: { drag: { x: false, y: false }, points: { show: false } },
  };
  const data = [xs, at((r) => r.lo), at((r) => r.hi), at((r) => r.median), at((r) => r.chosen)];
  // eslint-disable-next-line no-undef
  const u = new uPlot(opts, data, box);
  const line = frameCursor(u, n, onSeek);
  el.dataset.steps = String(recs.length);
  el.dataset.logged = recs.map((r) => r.t).join(',');
  return {
    setFrame(t) { line.style.left = `${u.valToPos(t, 'x')}px`; },
    destroy() { u.destroy(); el.replaceChildren(); delete el.dataset.steps; delete el.dataset.logged; },
  };
}
