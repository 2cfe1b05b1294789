// Human takeovers on the timeline: an episode whose steps carry the `intervention` flag (LeRobot's
// DAgger recordings, or a source's flag named at ingest) gets a strip under the scrub bar with a
// shaded span per run of steps a human controlled, and, for `validity`, a span per run of steps
// marked invalid. A span's click seeks to its first step; the strip's cursor follows the frame.

/** Runs of consecutive steps where `pred(value)` holds: [{start, end}] (end inclusive). */
export function runs(values, pred) {
  const out = [];
  let start = -1;
  for (let t = 0; t <= values.length; t++) {
    const on = t < values.length && pred(values[t]);
    if (on && start < 0) start = t;
    if (!on && start >= 0) { out.push({ start, end: t - 1 }); start = -1; }
  }
  return out;
}

/** Draws the takeover strip of a steps document (n frames) into `el`, under the range input
 *  `scrub` and as wide; returns {setFrame, destroy} like drawPlots. An episode without either
 *  flag leaves `el` hidden. */
export function drawTakeovers(el, scrub, steps, n, onSeek) {
  el.replaceChildren();
  const cols = (steps && steps.columns) || {};
  const kinds = [
    { col: 'intervention', cls: 'takeover', pred: (v) => v === true, what: 'human takeover' },
    { col: 'validity', cls: 'invalid', pred: (v) => v === false, what: 'marked invalid' },
  ];
  const spans = [];
  for (const k of kinds) {
    const v = cols[k.col];
    if (!Array.isArray(v)) continue;
    for (const r of runs(v, k.pred)) spans.push({ ...k, ...r });
  }
  const flagged = kinds.some((k) => Array.isArray(cols[k.col]));
  el.hidden = !flagged || n === 0;
  el.dataset.spans = String(spans.length);
  if (el.hidden) return { setFrame() {}, destroy() { el.replaceChildren(); } };
  const align = () => {
    const box = el.parentElement;
    const pad = parseFloat(getComputedStyle(box).paddingLeft) || 0;
    const left = scrub.getBoundingClientRect().left - box.getBoundingClientRect().left - pad;
    el.style.marginLeft = `${Math.max(0, left)}px`;
    el.style.width = `${scrub.offsetWidth}px`;
  };
  align();
  window.addEventListener('resize', align);
  // Positions as a share of the scrub range (frame 0 .. n-1); a span covers its steps' width.
  const pct = (t) => (n > 1 ? (100 * t) / n : 0);
  for (const s of spans) {
    const d = document.createElement('div');
    d.className = `span ${s.cls}`;
    d.dataset.start = String(s.start);
    d.dataset.end = String(s.end);
    d.style.left = `${pct(s.start)}%`;
    d.style.width = `${Math.max(pct(s.end + 1) - pct(s.start), 0.5)}%`;
    d.title = `${s.what}: steps ${s.start}–${s.end}`;
    d.addEventListener('click', () => onSeek(s.start));
    el.appendChild(d);
  }
  const cursor = document.createElement('div');
  cursor.className = 'cursor';
  el.appendChild(cursor);
  const legend = document.createElement('span');
  legend.className = 'legend';
  const taken = spans.filter((s) => s.cls === 'takeover');
  legend.textContent = taken.length
    ? `human takeover from step ${taken[0].start} (${taken.length} span${taken.length > 1 ? 's' : ''})`
    : (Array.isArray(cols.intervention) ? 'no human takeover' : '');
  el.appendChild(legend);
  return {
    setFrame(t) { cursor.style.left = `${pct(t)}%`; },
    destroy() {
      window.removeEventListener('resize', align);
      el.replaceChildren();
      el.hidden = true;
      delete el.dataset.spans;
    },
  };
}
