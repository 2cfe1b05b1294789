// Image cameras and the camera grid. An image camera is an image column of the episode's steps
// (robomimic `agentview_image`, a LeRobot `image` feature): one PNG per step, served one at a
// time by GET /v1/episodes/{id}/frames/{camera}/{t} (cached for good by the browser: a version's
// frames never change). Frames are loaded on demand around the step shown — a few ahead while
// paused or stepping, about a second ahead while playing, two behind — never the whole episode
// up front (episodes have thousands of steps). The `<img>` keeps showing the last frame loaded
// until the wanted one is decoded, so scrubbing never flashes empty.

import * as api from './api.js';

const BEHIND = 2;          // frames fetched behind the one shown
const AHEAD = 6;           // frames fetched ahead while paused or stepping
const AHEAD_SECONDS = 1.5; // while playing: this much time ahead
const INFLIGHT = 4;        // requests at once per camera
const KEEP = 96;           // decoded frames held per camera (the HTTP cache keeps the rest)

/** One image camera of an episode: an `<img>` showing the frame of the step asked for. */
export class ImageCamera {
  constructor(episodeId, cam, steps, fps) {
    this.id = episodeId;
    this.key = cam.name;
    this.n = steps;
    this.fps = fps || 10;
    this.el = document.createElement('img');
    this.el.className = 'cam';
    this.el.alt = `${cam.name} (camera)`;
    this.el.dataset.key = cam.name;
    this.el.dataset.frame = '';
    if (cam.shape) {
      // The frame's size before the first one arrives: the grid does not jump.
      this.el.width = cam.shape[1];
      this.el.height = cam.shape[0];
    }
    this.frames = new Map(); // step -> { img, state: 'loading' | 'ok' | 'failed', ready }
    this.want = -1;
    this.inflight = 0;
    this.playing = false;
    this.disposed = false;
  }

  /** The entry of step t, its request started when `start` and a slot is free. */
  entry(t, start) {
    let e = this.frames.get(t);
    if (e || !start) return e;
    const img = new Image();
    img.decoding = 'async';
    e = { img, state: 'loading' };
    this.inflight++;
    e.ready = new Promise((resolve) => {
      img.onload = () => {
        // decode() makes the swap in the visible <img> paint at once
        img.decode().catch(() => {}).then(() => resolve(true));
      };
      img.onerror = () => resolve(false);
    }).then((ok) => {
      e.state = ok ? 'ok' : 'failed';
      this.inflight--;
      if (!this.disposed) {
        if (ok && t === this.want) this.paint(t);
        this.pump();
      }
      return ok;
    });
    img.src = api.frameUrl(this.id, this.key, t);
    this.frames.set(t, e);
    return e;
  }

  paint(t) {
    const e = this.frames.get(t);
    if (!e || e.state !== 'ok') return;
    this.el.src = e.img.src;
    this.el.dataset.frame = String(t);
  }

  /** Shows step t (at once when loaded, else as soon as it is) and fetches the window around it. */
  show(t, playing) {
    if (this.disposed || this.n === 0) return;
    this.want = Math.max(0, Math.min(this.n - 1, t));
    this.playing = !!playing;
    const e = this.entry(this.want, true);
    if (e.state === 'ok') this.paint(this.want);
    this.pump();
    this.evict();
  }

  /** Whether step t has arrived (or failed: a missing frame never holds playback up). */
  loaded(t) {
    const e = this.frames.get(Math.max(0, Math.min(this.n - 1, t)));
    return !!e && e.state !== 'loading';
  }

  /** Resolves when the first frame shown is loaded (true) or has failed (false). */
  ready() {
    if (this.want < 0) this.show(0, false);
    const e = this.frames.get(this.want);
    return e ? e.ready : Promise.resolve(false);
  }

  /** The steps worth fetching now, nearest first: the one shown, those ahead, a few behind. */
  window() {
    const ahead = this.playing ? Math.max(AHEAD, Math.ceil(this.fps * AHEAD_SECONDS)) : AHEAD;
    const out = [this.want];
    for (let d = 1; d <= ahead; d++) {
      out.push(this.want + d);
      if (d <= BEHIND) out.push(this.want - d);
    }
    return out.filter((t) => t >= 0 && t < this.n);
  }

  pump() {
    for (const t of this.window()) {
      if (this.inflight >= INFLIGHT) return;
      this.entry(t, true);
    }
  }

  /** Drops the frames furthest from the one shown, past KEEP (loads in flight finish first). */
  evict() {
    if (this.frames.size <= KEEP) return;
    const far = [...this.frames.keys()]
      .filter((t) => this.frames.get(t).state !== 'loading')
      .sort((a, b) => Math.abs(b - this.want) - Math.abs(a - this.want));
    for (const t of far.slice(0, this.frames.size - KEEP)) this.frames.delete(t);
  }

  dispose() {
    this.disposed = true;
    for (const e of this.frames.values()) if (e.state === 'loading') e.img.removeAttribute('src');
    this.frames.clear();
    this.el.removeAttribute('src');
    this.el.remove();
  }
}

/** The image cameras an episode's detail lists (`cameras`, kind `image`). */
export function imageCameras(detail, id, steps, fps) {
  return ((detail && detail.cameras) || [])
    .filter((c) => c.kind === 'image')
    .map((c) => new ImageCamera(id, c, steps, fps));
}

/** Lays out `figures` (one per camera, in the detail's camera order) in a responsive grid:
 *  one camera large, two side by side, three or four in two columns, more in three; each smaller
 *  as there are more, so that the controls under them stay in view. */
export function layoutGrid(grid, figures, order) {
  const rank = new Map((order || []).map((c, i) => [c.name, i]));
  const key = (f) => (rank.has(f.dataset.key) ? rank.get(f.dataset.key) : 1e9);
  figures.sort((a, b) => key(a) - key(b));
  grid.replaceChildren(...figures);
  const n = figures.length;
  grid.style.setProperty('--cols', String(n <= 1 ? 1 : n <= 4 ? 2 : 3));
  grid.style.setProperty('--cam-h', `${n <= 1 ? 340 : n <= 2 ? 300 : n <= 4 ? 210 : 170}px`);
  grid.dataset.cameras = String(n);
  grid.hidden = n === 0;
}
