// Time plots of the action and state dimensions (uPlot, vendored) with a cursor at the current
// frame, and a 2-D / 3-D trajectory sketch for episodes without video.

const PALETTE = ['#1f77b4', '#ff7f0e', '#2ca02c', '#d62728', '#9467bd', '#8c564b', '#e377c2', '#7f7f7f',
  '#bcbd22', '#17becf'];

/** The vector columns of a steps document worth plotting: action first, then observations. */
export function vectorColumns(steps) {
  const cols = steps.columns || {};
  const out = [];
  const add = (name, label) => {
    const v = cols[name];
    if (!Array.isArray(v) || v.length === 0) return;
    const first = v.find((x) => x !== null);
    if (Array.isArray(first) && first.length > 0 && first.length <= 64 && typeof first[0] === 'number') {
      out.push({ name, label, dim: first.length, rows: v });
    } else if (typeof first === 'number') {
      out.push({ name, label, dim: 1, rows: v.map((x) => [x]) });
    }
  };
  add('action', 'action');
  for (const name of Object.keys(cols).sort()) {
    if (name.startsWith('obs.')) add(name, name.slice(4));
  }
  add('reward', 'reward');
  return out;
}

/** The frame cursor of a uPlot chart `u` over an episode of `n` frames: a vertical line (moved by
 *  the caller to the frame shown) and click-to-seek (`onSeek(frame)`). Every timeline plot
 *  (these, the verifier score, the steering spread) uses it. */
export function frameCursor(u, n, onSeek) {
  const line = document.createElement('div');
  line.className = 'frame-cursor';
  u.over.appendChild(line);
  u.over.addEventListener('click', (e) => {
    const f = Math.round(u.posToVal(e.offsetX, 'x'));
    if (Number.isFinite(f)) onSeek(Math.max(0, Math.min(n - 1, f)));
  });
  return line;
}

/** Draws one chart per vector column into `el`; `onSeek(frame)` on a click. */
export function drawPlots(el, steps, onSeek) {
  el.replaceChildren();
  const n = steps.num_rows || 0;
  const xs = Array.from({ length: n }, (_, i) => i);
  const charts = [];
  const width = Math.max(320, el.clientWidth - 8);
  for (const col of vectorColumns(steps)) {
    const box = document.createElement('div');
    box.className = 'plot';
    el.appendChild(box);
    const data = [xs];
    const series = [{ label: 'frame' }];
    for (let d = 0; d < col.dim; d++) {
      data.push(col.rows.map((r) => (r && typeof r[d] === 'number' ? r[d] : null)));
      series.push({ label: col.dim === 1 ? col.label : `${col.label}[${d}]`, stroke: PALETTE[d % PALETTE.length], width: 1.5 });
    }
    const opts = {
      title: col.label, width, height: 150, series,
      scales: { x: { time: false } },
      axes: [{ size: 28 }, { size: 48 }],
      legend: { show: col.dim <= 8 },
      cursor: { drag: { x: false, y: false }, points: { show: false } },
    };
    // eslint-disable-next-line no-undef
    const u = new uPlot(opts, data, box);
    const line = frameCursor(u, n, onSeek);
    charts.push({ u, line });
  }
  return {
    count: charts.length,
    setFrame(t) {
      for (const c of charts) c.line.style.left = `${c.u.valToPos(t, 'x')}px`;
    },
    destroy() {
      for (const c of charts) c.u.destroy();
      el.replaceChildren();
    },
  };
}

/** A trajectory sketch of the best position-like vector (2-D, or 3-D rotatable by dragging). */
export function drawTrajectory(canvas, steps) {
  const cols = vectorColumns(steps).filter((c) => c.name !== 'reward');
  const score = (c) => (/pos|eef|xyz|position/i.test(c.name) ? 0 : c.name.startsWith('obs.') ? 1 : 2);
  cols.sort((a, b) => score(a) - score(b));
  const col = cols.find((c) => c.dim >= 2);
  const ctx = canvas.getContext('2d');
  let frame = 0;
  let yaw = 0.6;
  let pitch = 0.5;
  if (!col) {
    return { setFrame() {}, destroy() {}, label: 'none' };
  }
  const dim3 = col.dim >= 3;
  const pts = col.rows.map((r) => [r[0] || 0, r[1] || 0, dim3 ? r[2] || 0 : 0]);
  const lo = [0, 1, 2].map((k) => Math.min(...pts.map((p) => p[k])));
  const hi = [0, 1, 2].map((k) => Math.max(...pts.map((p) => p[k])));
  const norm = pts.map((p) => p.map((v, k) => (hi[k] > lo[k] ? (v - lo[k]) / (hi[k] - lo[k]) - 0.5 : 0)));
  const project = (p) => {
    if (!dim3) return [p[0], -p[1]];
    const [x, y, z] = p;
    const cx = Math.cos(yaw) * x - Math.sin(yaw) * y;
    const cy = Math.sin(yaw) * x + Math.cos(yaw) * y;
    return [cx, -(Math.cos(pitch) * z - Math.sin(pitch) * cy)];
  };
  const draw = () => {
    const w = canvas.width;
    const h = canvas.height;
    ctx.clearRect(0, 0, w, h);
    const s = Math.min(w, h) * (dim3 ? 0.8 : 0.85);
    const xy = norm.map(project).map(([a, b]) => [w / 2 + a * s, h / 2 + b * s]);
    for (let i = 1; i < xy.length; i++) {
      ctx.strokeStyle = `hsl(${220 - 200 * (i / xy.length)}, 70%, 45%)`;
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.moveTo(...xy[i - 1]);
      ctx.lineTo(...xy[i]);
      ctx.stroke();
    }
    const dot = (p, color, r) => { ctx.fillStyle = color; ctx.beginPath(); ctx.arc(p[0], p[1], r, 0, 7); ctx.fill(); };
    if (xy.length) {
      dot(xy[0], '#2ca02c', 5);
      dot(xy[xy.length - 1], '#d62728', 5);
      dot(xy[Math.min(frame, xy.length - 1)], '#111', 6);
    }
    ctx.fillStyle = '#444';
    ctx.font = '12px sans-serif';
    ctx.fillText(`${col.label}[0..${dim3 ? 2 : 1}] ${dim3 ? '3-D (drag to rotate)' : '2-D'} · start green, end red`, 8, 16);
  };
  let drag = null;
  const down = (e) => { drag = [e.clientX, e.clientY, yaw, pitch]; };
  const move = (e) => {
    if (!drag || !dim3) return;
    yaw = drag[2] + (e.clientX - drag[0]) / 100;
    pitch = drag[3] + (e.clientY - drag[1]) / 100;
    draw();
  };
  const up = () => { drag = null; };
  canvas.addEventListener('pointerdown', down);
  window.addEventListener('pointermove', move);
  window.addEventListener('pointerup', up);
  draw();
  return {
    label: col.label,
    setFrame(t) { frame = t; draw(); },
    destroy() {
      canvas.removeEventListener('pointerdown', down);
      window.removeEventListener('pointermove', move);
      window.removeEventListener('pointerup', up);
      ctx.clearRect(0, 0, canvas.width, canvas.height);
    },
  };
}
