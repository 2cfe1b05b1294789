// Episodes made ready to show (metadata, steps, every camera's video element seeked to the
// episode's first frame and every image camera's first frame loaded, so that switching to a
// prefetched episode is instant), and the player that keeps all cameras in sync under one scrub
// bar. Image cameras (one PNG per step, `cameras.js`) follow the frame shown.
//
// LeRobot v3.0 packs many episodes into one mp4 per camera: the steps' `media.<key>.timestamp`
// column holds each frame's time inside that file (the episode's `from_timestamp` + its own
// timestamp), so the player seeks and clamps by those times, never past the episode's frames.

import * as api from './api.js';
import { imageCameras, layoutGrid } from './cameras.js';

const EPS = 1e-3; // seek a hair past the frame's timestamp so the decoder lands on that frame

/** The media keys of a steps document, with the per-frame times. */
export function cameras(steps) {
  const cols = steps.columns || {};
  const out = [];
  for (const name of Object.keys(cols).sort()) {
    const m = /^media\.(.+)\.path$/.exec(name);
    if (!m) continue;
    const ts = cols[`media.${m[1]}.timestamp`];
    if (!Array.isArray(ts) || ts.length === 0) continue;
    out.push({ key: m[1], ts });
  }
  return out;
}

function fpsOf(ts, fallback) {
  if (ts && ts.length > 1) {
    const d = (ts[ts.length - 1] - ts[0]) / (ts.length - 1);
    if (d > 0) return 1 / d;
  }
  return fallback || 10;
}

function waitFor(el, events, ok, timeoutMs) {
  return new Promise((resolve) => {
    if (ok()) { resolve(true); return; }
    const done = (v) => {
      clearTimeout(timer);
      for (const e of events) el.removeEventListener(e, check);
      resolve(v);
    };
    const check = () => { if (ok()) done(true); };
    const timer = setTimeout(() => done(ok()), timeoutMs);
    for (const e of events) el.addEventListener(e, check);
  });
}

/** Starts loading an episode; `loaded` resolves with detail+steps, `ready` when every video can play. */
export function prepare(id, limbo) {
  const p = { id, detail: null, steps: null, cams: [], imgs: [], error: null, disposed: false };
  p.loaded = Promise.all([api.episode(id), api.steps(id)]).then(([detail, steps]) => {
    p.detail = detail;
    p.steps = steps;
    if (p.disposed) return p;
    for (const c of cameras(steps)) {
      const el = document.createElement('video');
      el.muted = true;
      el.playsInline = true;
      el.preload = 'auto';
      el.dataset.key = c.key;
      el.src = api.mediaUrl(id, c.key);
      limbo.appendChild(el);
      p.cams.push({ key: c.key, ts: c.ts, el });
    }
    const n = steps.num_rows || 0;
    p.imgs = imageCameras(detail, id, n, fpsOf(steps.columns && steps.columns.timestamp, 10));
    for (const c of p.imgs) limbo.appendChild(c.el);
    return p;
  }).catch((e) => { p.error = e; return p; });
  p.ready = p.loaded.then(async () => {
    if (p.error) return false;
    const oks = await Promise.all(p.cams.map(async (c) => {
      const el = c.el;
      if (!(await waitFor(el, ['loadedmetadata', 'error'], () => el.readyState >= 1 || !!el.error, 15000))) return false;
      if (el.error) return false;
      const target = c.ts[0] + EPS;
      if (Math.abs(el.currentTime - target) > 1e-4) {
        el.currentTime = target;
        await waitFor(el, ['seeked', 'error'], () => !el.seeking, 15000);
      }
      return waitFor(el, ['canplay', 'canplaythrough', 'error'], () => el.readyState >= 3 || !!el.error, 15000)
        .then(() => el.readyState >= 3);
    }));
    const imgs = await Promise.all(p.imgs.map((c) => c.ready()));
    return oks.every(Boolean) && imgs.every(Boolean);
  });
  return p;
}

/** Frees a prepared episode's video elements. */
export function dispose(p) {
  p.disposed = true;
  for (const c of p.cams) {
    c.el.pause();
    c.el.removeAttribute('src');
    c.el.load();
    c.el.remove();
  }
  p.cams = [];
  for (const c of p.imgs) c.dispose();
  p.imgs = [];
}

/** The synchronized player: cameras in `grid`, one scrub bar, frame stepping, play/pause. */
export class Player {
  constructor({ grid, scrub, frameOut, playButton, onFrame }) {
    Object.assign(this, { grid, scrub, frameOut, playButton, onFrame });
    this.p = null;
    this.n = 0;
    this.frame = 0;
    this.playing = false;
    this.timer = null;
    this.raf = 0;
    scrub.addEventListener('input', () => this.seek(Number(scrub.value)));
  }

  /** Shows a prepared (loaded) episode; its video elements move from the limbo into the grid. */
  attach(p, limbo) {
    this.pause();
    if (this.p && this.p !== p) for (const c of [...this.p.cams, ...this.p.imgs]) limbo.appendChild(c.el);
    this.p = p;
    this.n = (p.steps && p.steps.num_rows) || 0;
    const ts = (p.steps && p.steps.columns && p.steps.columns.timestamp) || null;
    this.fps = fpsOf(p.cams.length ? p.cams[0].ts : ts, 10);
    const figures = [...p.cams, ...p.imgs].map((c) => {
      const fig = document.createElement('figure');
      fig.dataset.key = c.key;
      fig.appendChild(c.el);
      const cap = document.createElement('figcaption');
      cap.textContent = c.key;
      fig.appendChild(cap);
      c.el.onclick = () => this.toggle();
      return fig;
    });
    layoutGrid(this.grid, figures, p.detail && p.detail.cameras);
    this.scrub.max = String(Math.max(0, this.n - 1));
    this.seek(0);
  }

  hasVideo() { return !!(this.p && this.p.cams.length); }

  /** Whether the episode on screen has any camera (video or image). */
  hasCameras() { return !!(this.p && (this.p.cams.length || this.p.imgs.length)); }

  /** The frame shown by a camera at its current time. */
  frameAt(c) {
    const t = c.el.currentTime + EPS * 2;
    const ts = c.ts;
    let lo = 0;
    let hi = ts.length - 1;
    if (t < ts[0]) return 0;
    while (lo < hi) {
      const mid = (lo + hi + 1) >> 1;
      if (ts[mid] <= t) lo = mid; else hi = mid - 1;
    }
    return lo;
  }

  seek(f) {
    if (!this.p || this.n === 0) return;
    f = Math.max(0, Math.min(this.n - 1, Math.round(f)));
    if (this.playing) this.pause();
    for (const c of this.p.cams) {
      const target = c.ts[Math.min(f, c.ts.length - 1)] + EPS;
      if (Math.abs(c.el.currentTime - target) > 1e-4) c.el.currentTime = target;
    }
    this.show(f);
  }

  step(d) { this.seek(this.frame + d); }

  show(f) {
    this.frame = f;
    this.scrub.value = String(f);
    const t = (this.p.steps.columns.timestamp || [])[f];
    this.frameOut.textContent = `frame ${f + 1} / ${this.n}${typeof t === 'number' ? ` · ${t.toFixed(2)} s` : ''}`;
    for (const c of this.p.imgs) c.show(f, this.playing);
    this.onFrame(f);
  }

  toggle() { if (this.playing) this.pause(); else this.play(); }

  play() {
    if (!this.p || this.n === 0) return;
    if (this.frame >= this.n - 1) this.seek(0);
    this.playing = true;
    this.playButton.textContent = '❚❚';
    for (const c of this.p.imgs) c.show(this.frame, true); // widen the prefetch window
    if (!this.hasVideo()) {
      this.timer = setInterval(() => {
        if (this.frame >= this.n - 1) { this.pause(); return; }
        // Image cameras move together: wait (this tick) for a frame still on its way.
        if (this.p.imgs.some((c) => !c.loaded(this.frame + 1))) return;
        this.show(this.frame + 1);
      }, 1000 / this.fps);
      return;
    }
    for (const c of this.p.cams) c.el.play().catch(() => {});
    const tick = () => {
      if (!this.playing) return;
      const cams = this.p.cams;
      const master = cams[0];
      const f = this.frameAt(master);
      const end = master.ts[Math.min(this.n, master.ts.length) - 1] + 0.5 / this.fps;
      if (master.el.currentTime >= end || master.el.ended) {
        this.pause();
        this.seek(this.n - 1);
        return;
      }
      // A play() that a pending seek interrupted rejects and leaves the camera paused: ask again
      // (every camera, the master too) until it plays, instead of a player stuck on one frame.
      if (master.el.paused) master.el.play().catch(() => {});
      const offset = master.el.currentTime - master.ts[f];
      for (const c of cams.slice(1)) {
        const want = c.ts[Math.min(f, c.ts.length - 1)] + offset;
        if (Math.abs(c.el.currentTime - want) > 0.08) c.el.currentTime = want;
        if (c.el.paused) c.el.play().catch(() => {});
      }
      if (f !== this.frame) this.show(f);
      this.raf = requestAnimationFrame(tick);
    };
    this.raf = requestAnimationFrame(tick);
  }

  pause() {
    this.playing = false;
    this.playButton.textContent = '▶';
    clearInterval(this.timer);
    cancelAnimationFrame(this.raf);
    if (this.p) for (const c of this.p.cams) c.el.pause();
  }
}
