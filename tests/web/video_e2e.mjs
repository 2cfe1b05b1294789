// The labeling page plays a robomimic file's two cameras stored as H.264 video (`ufops ingest
// --images video`) in real headless Chromium (Debian's `chromium`, driven by playwright-core).
// Started by tests/web_labeling.rs (robomimic_video_cameras_in_headless_chromium) against
// `ufops serve` on loopback. It checks that Chromium decodes the codec, not only that the
// elements exist: each camera's video reaches readyState >= 2 with its real size, and the
// pixels drawn from it are the file's (agentview's background is (0, 0, 90) in episode 0; the
// gripper camera's is gray 60) and change as the frame is stepped. Screenshot
// `robomimic_video_cameras.png`.
//
// Env: UFOPS_URL, UFOPS_TOKEN (a labeler), UFOPS_POLICY, UFOPS_ARTIFACTS, CHROMIUM. Prints
// `E2E_RESULT <json>`.

import { chromium } from 'playwright-core';
import { mkdirSync } from 'node:fs';
import { join } from 'node:path';

const URL = process.env.UFOPS_URL;
const TOKEN = process.env.UFOPS_TOKEN;
const POLICY = process.env.UFOPS_POLICY;
const OUT = process.env.UFOPS_ARTIFACTS || 'artifacts';
const EXE = process.env.CHROMIUM || '/usr/bin/chromium';
if (!URL || !TOKEN || !POLICY) {
  console.error('set UFOPS_URL, UFOPS_TOKEN and UFOPS_POLICY');
  process.exit(2);
}
mkdirSync(OUT, { recursive: true });
const log = (...a) => console.log('[video-e2e]', ...a);
function check(cond, msg) {
  if (!cond) throw new Error(`check failed: ${msg}`);
}

const browser = await chromium.launch({
  executablePath: EXE,
  headless: true,
  args: ['--no-sandbox', '--autoplay-policy=no-user-gesture-required', '--disable-dev-shm-usage'],
});
const result = {};
try {
  const ctx = await browser.newContext({ viewport: { width: 1440, height: 1000 } });
  const a = await ctx.newPage();
  const errors = [];
  // (the browser logs the 401 before sign-in and other 4xx as "Failed to load resource", as in label_e2e.mjs)
  a.on('console', (m) => { if (m.type() === 'error' && !m.text().startsWith('Failed to load resource')) errors.push(m.text()); });
  a.on('pageerror', (e) => errors.push(String(e)));
  await a.goto(`${URL}/ui/#policy=${POLICY}`);
  await a.fill('#token', TOKEN);
  await a.keyboard.press('Enter');
  await a.waitForSelector('#app:not([hidden])');
  await a.waitForFunction(() => document.body.dataset.ready, null, { timeout: 30000 });
  // Every camera: what the video element says and the mean colour of a patch of its current
  // picture (drawn onto a canvas: only a decoded frame has pixels).
  const cams = () => a.evaluate(() => [...document.querySelectorAll('#videos video')].map((v) => {
    const out = { key: v.dataset.key, rs: v.readyState, w: v.videoWidth, h: v.videoHeight, t: v.currentTime, err: v.error && v.error.code };
    if (v.readyState >= 2 && v.videoWidth > 0) {
      const c = document.createElement('canvas');
      c.width = v.videoWidth; c.height = v.videoHeight;
      const g = c.getContext('2d');
      g.drawImage(v, 0, 0);
      const px = g.getImageData(0, 0, c.width, c.height).data;
      // the top-left 8×8 patch (background in both cameras) and a hash of the whole picture
      const mean = [0, 0, 0];
      for (let y = 0; y < 8; y++) for (let x = 4; x < 12; x++) for (let k = 0; k < 3; k++) mean[k] += px[(y * c.width + x) * 4 + k] / 64;
      out.patch = mean.map(Math.round);
      let hash = 0;
      for (let i = 0; i < px.length; i += 4) hash = (hash * 31 + px[i] + px[i + 1] * 7 + px[i + 2] * 13) >>> 0;
      out.hash = hash;
    }
    return out;
  }));
  const decoded = () => a.waitForFunction(() => {
    const vs = [...document.querySelectorAll('#videos video')];
    return vs.length > 0 && vs.every((v) => v.readyState >= 2 && !v.seeking && v.videoWidth > 0);
  }, null, { timeout: 20000 });
  await decoded();
  const c0 = await cams();
  log('cameras at frame 0', JSON.stringify(c0));
  check(c0.length === 2, `two video cameras: ${JSON.stringify(c0)}`);
  check(c0.map((c) => c.key).join() === 'agentview_image,robot0_eye_in_hand_image', `camera names: ${c0.map((c) => c.key)}`);
  check(c0.every((c) => c.w === 84 && c.h === 84 && !c.err), `decoded at the cameras' 84x84: ${JSON.stringify(c0)}`);
  check(await a.evaluate(() => document.querySelectorAll('#videos img.cam').length === 0), 'no image element for video cameras');
  const near = (p, want, tol) => p && p.every((v, k) => Math.abs(v - want[k]) <= tol);
  // The episode shown first is one of the two demos: agentview's blue background is 90 or 130.
  const agent = c0[0].patch;
  check(near(agent, [0, 0, 90], 12) || near(agent, [0, 0, 130], 12), `agentview background decoded: ${JSON.stringify(agent)}`);
  check(near(c0[1].patch, [60, 60, 60], 12), `gripper camera background decoded: ${JSON.stringify(c0[1].patch)}`);
  // Stepping: both cameras move to the frame's time and show another picture.
  for (let k = 0; k < 5; k++) await a.keyboard.press('.');
  await a.waitForFunction(() => document.getElementById('scrub').value === '5', null, { timeout: 10000 });
  await decoded();
  const c5 = await cams();
  log('cameras at frame 5', JSON.stringify(c5));
  check(c5.every((c, i) => c.t > c0[i].t && c.hash !== c0[i].hash), `stepping changed every camera's picture: ${JSON.stringify(c5)}`);
  // Playing advances both.
  await a.keyboard.press(' ');
  const played = await a.waitForFunction(() => Number(document.getElementById('scrub').value) > 15, null, { timeout: 15000 })
    .then(() => true, () => false);
  await a.keyboard.press(' ');
  check(played, 'playing advanced the frame');
  await decoded();
  const shotPath = join(OUT, 'robomimic_video_cameras.png');
  await a.evaluate(() => window.scrollTo(0, 0));
  await a.screenshot({ path: shotPath, fullPage: true });
  log('screenshot', shotPath);
  check(errors.length === 0, `no errors in the page console: ${errors.join(' | ')}`);
  result.cameras = c5.length;
  result.frame0 = c0;
  result.frame5 = c5;
  await ctx.close();
} finally {
  await browser.close();
}
console.log(`E2E_RESULT ${JSON.stringify(result)}`);
