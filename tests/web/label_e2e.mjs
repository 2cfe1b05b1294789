// End-to-end test of the labeling page in real headless Chromium (Debian's `chromium`, driven by
// playwright-core). Started by tests/web_labeling.rs against `ufops serve` on loopback with the
// LeRobot v3.0 video fixture ingested (labels reset to unknown: a labeling campaign), and the
// v3.0 fixture without video under policy `lowdim`, and (when UFOPS_IMAGE_POLICY names it) a
// robomimic file with two image cameras: both shown, frames loaded on demand, following the
// timeline when stepping, scrubbing and playing (screenshot `robomimic_cameras.png`).
//
// Env: UFOPS_URL, UFOPS_TOKEN_A / UFOPS_TOKEN_B (two labelers), UFOPS_ARTIFACTS (screenshots),
// CHROMIUM (default /usr/bin/chromium). Prints `E2E_RESULT <json>` for the Rust test to verify
// through the API, and the labeling-speed figures.

import { chromium } from 'playwright-core';
import { mkdirSync } from 'node:fs';
import { join } from 'node:path';

const URL = process.env.UFOPS_URL;
const TOKEN_A = process.env.UFOPS_TOKEN_A;
const TOKEN_B = process.env.UFOPS_TOKEN_B;
const OUT = process.env.UFOPS_ARTIFACTS || 'artifacts';
const EXE = process.env.CHROMIUM || '/usr/bin/chromium';
if (!URL || !TOKEN_A || !TOKEN_B) {
  console.error('set UFOPS_URL, UFOPS_TOKEN_A and UFOPS_TOKEN_B');
  process.exit(2);
}
mkdirSync(OUT, { recursive: true });

const log = (...a) => console.log('[e2e]', ...a);
function check(cond, msg) {
  if (!cond) throw new Error(`check failed: ${msg}`);
}
const shot = async (page, name) => {
  const path = join(OUT, `${name}.png`);
  await page.screenshot({ path, fullPage: true });
  log('screenshot', path);
};
const stats = (xs) => {
  const v = [...xs].sort((a, b) => a - b);
  return { n: v.length, median: v.length ? v[v.length >> 1] : null, max: v.length ? v[v.length - 1] : null };
};

const browser = await chromium.launch({
  executablePath: EXE,
  headless: true,
  args: ['--no-sandbox', '--autoplay-policy=no-user-gesture-required', '--disable-dev-shm-usage'],
});
const result = { labeled: [], conflict: null, key_presses: 0 };
try {
  // ---------------------------------------------------------------- session A signs in
  const ctxA = await browser.newContext({ viewport: { width: 1440, height: 1000 } });
  const a = await ctxA.newPage();
  const consoleErrors = [];
  // (the browser logs every 4xx the test provokes — 401 before sign-in, 409, 403 — as "Failed to load resource")
  a.on('console', (m) => { if (m.type() === 'error' && !m.text().startsWith('Failed to load resource')) consoleErrors.push(m.text()); });
  a.on('pageerror', (e) => consoleErrors.push(String(e)));
  // Every episode list and count the page asks for: it pages (here 3 at a time) and counts on
  // the server; it never reads the whole campaign.
  const apiCalls = [];
  a.on('request', (r) => {
    const u = new globalThis.URL(r.url());
    if (u.pathname.startsWith('/v1/episodes') && !u.pathname.includes('/media/')) apiCalls.push(u.pathname + u.search);
  });
  await a.goto(`${URL}/ui/#policy=toy-dp&pagesize=3`);
  await a.waitForSelector('#signin:not([hidden])');
  await shot(a, '01-sign-in');
  // a wrong token is refused
  await a.fill('#token', 'not-a-token');
  await a.keyboard.press('Enter');
  await a.waitForFunction(() => document.getElementById('signin-error').textContent.includes('unknown'));
  await a.fill('#token', TOKEN_A);
  await a.keyboard.press('Enter');
  await a.waitForSelector('#app:not([hidden])');
  await a.waitForFunction(() => document.body.dataset.ready, null, { timeout: 20000 });
  const me = await a.textContent('#me');
  check(me.includes('alice'), `signed in as alice, header says ${me}`);
  const cookies = await ctxA.cookies();
  const sess = cookies.find((c) => c.name === 'ufops_session');
  check(sess && sess.httpOnly && sess.sameSite === 'Strict', `HttpOnly SameSite=Strict session cookie: ${JSON.stringify(sess)}`);
  check(await a.evaluate(() => !document.cookie.includes('ufops_session')), 'the cookie is not readable by scripts');
  const first = await a.evaluate(() => ({
    id: document.body.dataset.episode,
    videos: [...document.querySelectorAll('#videos video')].map((v) => ({ rs: v.readyState, t: v.currentTime, w: v.videoWidth })),
    plots: document.querySelectorAll('#plots .uplot').length,
    counts: document.getElementById('counts').textContent,
    progress: document.getElementById('progress-text').textContent,
    loaded: window.ufops.state.queue.length,
  }));
  log('first episode', JSON.stringify(first));
  check(first.videos.length >= 1 && first.videos.every((v) => v.rs >= 3 && v.w > 0), 'the first episode\'s video is playable');
  check(first.plots >= 2, 'action and state plots are drawn');
  check(/unknown 8/.test(first.counts), `counts per state: ${first.counts}`);
  check(first.progress.startsWith('0 / 8'), `progress before labeling: ${first.progress}`);
  check(first.loaded === 3, `one page of 3 loaded at first (${first.loaded})`);
  await shot(a, '02-queue-and-episode');

  // the player: frame stepping and play/pause keep the cameras and the plot cursor on the frame
  await a.keyboard.press('.');
  await a.keyboard.press('.');
  const stepped = await a.evaluate(() => window.ufops.state && document.getElementById('scrub').value);
  check(stepped === '2', `two frame steps → frame 2 (scrub says ${stepped})`);
  await a.keyboard.press(',');
  await a.keyboard.press(' ');
  // Wait for the condition rather than a fixed time (a loaded machine plays late).
  const advanced = await a.waitForFunction(() => Number(document.getElementById('scrub').value) > 1, null, { timeout: 30000 })
    .then(() => true, () => false);
  await a.keyboard.press(' ');
  const played = await a.evaluate(() => Number(document.getElementById('scrub').value));
  check(advanced && played > 1, `playing advanced the frame (now ${played})`);
  const vt = await a.evaluate(() => [...document.querySelectorAll('#videos video')].map((v) => v.paused));
  check(vt.every(Boolean), 'space paused every camera');
  await shot(a, '03-playing');

  // ---------------------------------------------------------------- three verdicts, keyboard only
  const wallMs = [];
  for (const key of ['s', 'f', 's']) {
    const before = await a.evaluate(() => document.body.dataset.ready);
    const t0 = Date.now();
    await a.keyboard.press(key);
    result.key_presses++;
    await a.waitForFunction((prev) => document.body.dataset.ready && document.body.dataset.ready !== prev, before, { timeout: 15000 });
    wallMs.push(Date.now() - t0);
    const after = await a.evaluate(() => document.body.dataset.ready);
    const label = key === 's' ? 'success' : 'failure';
    result.labeled.push({ episode_id: before, label });
    const nextLabel = await a.evaluate((id) => window.ufops.state.queue.find((e) => e.id === id).label, after);
    check(nextLabel === 'unknown', `auto-advanced to an unlabeled episode (${after} is ${nextLabel})`);
    log(`pressed ${key} on ${before} → auto-advanced to ${after} in ${wallMs[wallMs.length - 1]} ms`);
  }
  await a.waitForFunction(() => window.ufops.state.queue.every((e) => !e.pending));
  // in-page: from the keydown event's timestamp to every video of the next episode at
  // readyState >= 3 on its first frame, with its plots drawn
  const inPageMs = await a.evaluate(() => window.ufops.metrics.advances.map((x) => x.ms));
  const inPageKeys = await a.evaluate(() => window.ufops.metrics.keyActions);
  log('in-page verdict → playable (ms):', inPageMs.map((x) => x.toFixed(1)).join(', '), `key actions so far: ${inPageKeys}`);
  check(inPageMs.length === 3, `three measured advances (${inPageMs.length})`);
  await shot(a, '04-three-labeled');
  const progress = await a.textContent('#progress-text');
  check(progress.startsWith('3 / 8'), `progress bar: ${progress}`);
  const loaded = await a.evaluate(() => window.ufops.state.queue.length);
  check(loaded > 3, `the queue loaded more pages as the labeler moved (${loaded} loaded)`);
  const lists = apiCalls.filter((u) => /^\/v1\/episodes\?/.test(u));
  check(lists.length >= 2 && lists.every((u) => /[?&]limit=3(&|$)/.test(u)), `pages of 3: ${lists.join(' ')}`);
  check(apiCalls.some((u) => u.startsWith('/v1/episodes/counts?')), `counts from the server: ${apiCalls.join(' ')}`);

  // ---------------------------------------------------------------- a conflict from a second session
  const stale = await a.evaluate(() => document.body.dataset.ready);
  const ctxB = await browser.newContext({ viewport: { width: 1440, height: 1000 } });
  const b = await ctxB.newPage();
  await b.goto(`${URL}/ui/#ep=${stale}`);
  await b.fill('#token', TOKEN_B);
  await b.keyboard.press('Enter');
  await b.waitForFunction((id) => document.body.dataset.ready === id, stale, { timeout: 20000 });
  await b.keyboard.press('f');
  await b.waitForFunction(() => window.ufops.state.queue.every((e) => !e.pending));
  await shot(b, '05-bob-labeled-failure');
  // A still shows the old revision and says success
  await a.keyboard.press('s');
  result.key_presses++;
  await a.waitForSelector('#conflict[open]', { timeout: 10000 });
  const text = await a.textContent('#conflict-text');
  check(text.includes('bob') && text.includes('failure'), `the conflict names who changed it and the current label: ${text}`);
  await shot(a, '06-conflict');
  // resolve: apply mine (keyboard: Tab from "Keep theirs" to "Apply mine", Enter)
  await a.keyboard.press('Tab');
  const focused = await a.evaluate(() => document.activeElement && document.activeElement.id);
  check(focused === 'conflict-mine', `Tab moves to "Apply mine" (focus on ${focused})`);
  await a.keyboard.press('Enter');
  await a.waitForFunction(() => !document.getElementById('conflict').open);
  await a.waitForFunction((id) => {
    const e = window.ufops.state.queue.find((x) => x.id === id);
    return e && !e.pending && e.label === 'success';
  }, stale, { timeout: 10000 });
  result.conflict = { episode_id: stale, first: { actor: 'bob', label: 'failure' }, final: { actor: 'alice', label: 'success' } };
  result.labeled.push({ episode_id: stale, label: 'success' });
  await a.evaluate((id) => { location.hash = `policy=toy-dp&ep=${id}`; }, stale);
  await a.reload();
  await a.waitForFunction((id) => document.body.dataset.ready === id, stale, { timeout: 20000 });
  const hist = await a.textContent('#history');
  check(hist.includes('bob') && hist.includes('alice'), `history shows both labelers: ${hist}`);
  await a.locator('#history').scrollIntoViewIfNeeded();
  await shot(a, '07-conflict-resolved-history');

  // ---------------------------------------------------------------- CSRF and bulk
  const csrf = await a.evaluate(async () => {
    const r = await fetch('/v1/labels/bulk', { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: '{"updates":[]}' });
    return r.status;
  });
  check(csrf === 403, `a cookie-authenticated write without X-Ufops-UI is refused (got ${csrf})`);
  // bulk: select two unknown episodes with x and label them failure with the bulk button
  await a.selectOption('#f-label', 'unknown');
  await a.waitForFunction(() => document.body.dataset.ready);
  await a.locator('#queue-list li input').nth(0).check();
  await a.locator('#queue-list li input').nth(1).check();
  const bulkIds = await a.evaluate(() => [...window.ufops.state.selected]);
  check(bulkIds.length === 2, `two selected (${bulkIds})`);
  await a.click('[data-bulk="failure"]');
  await a.waitForFunction(() => /2 episodes labeled failure/.test(document.getElementById('bulk-status').textContent));
  for (const id of bulkIds) result.labeled.push({ episode_id: id, label: 'failure', bulk: true });
  await shot(a, '08-bulk');
  // The counts and progress shown are the server's, after every write of this session.
  const server = await a.evaluate(async () => (await fetch('/v1/episodes/counts?policy=toy-dp')).json());
  check(server.total === 8 && server.unknown === 8 - result.labeled.length, `server counts: ${JSON.stringify(server)}`);
  const want = `success ${server.success} failure ${server.failure} unknown ${server.unknown}`;
  await a.waitForFunction((w) => document.getElementById('counts').textContent.replace(/\s+/g, ' ').trim() === w, want, { timeout: 10000 });
  const shown = await a.textContent('#progress-text');
  check(shown.startsWith(`${server.success + server.failure} / 8`), `progress after bulk: ${shown}`);
  result.counts = server;

  // ---------------------------------------------------------------- low-dim episode: plots and trajectory sketch
  await a.goto(`${URL}/ui/#policy=lowdim`);
  await a.reload();
  await a.waitForFunction(() => document.body.dataset.ready, null, { timeout: 20000 });
  const low = await a.evaluate(() => ({
    videos: document.querySelectorAll('#videos video').length,
    images: document.querySelectorAll('#videos img.cam').length,
    traj: !document.getElementById('traj').hidden,
    plots: document.querySelectorAll('#plots .uplot').length,
  }));
  check(low.videos === 0 && low.traj && low.plots >= 1, `no-video episode shows plots and a trajectory: ${JSON.stringify(low)}`);
  // its LeRobot `image` feature (PNGs in the data parquet) is an image camera
  check(low.images === 1, `the no-video episode's image feature is shown as a camera: ${JSON.stringify(low)}`);
  await a.keyboard.press('.');
  await shot(a, '09-low-dim-trajectory');

  // ---------------------------------------------------------------- image cameras (robomimic PNG columns)
  const IMAGE_POLICY = process.env.UFOPS_IMAGE_POLICY;
  if (IMAGE_POLICY) {
    const frameReqs = [];
    const onReq = (r) => { if (r.url().includes('/frames/')) frameReqs.push(new globalThis.URL(r.url()).pathname); };
    a.on('request', onReq);
    await a.goto(`${URL}/ui/#policy=${IMAGE_POLICY}`);
    await a.reload();
    await a.waitForFunction(() => document.body.dataset.ready, null, { timeout: 20000 });
    const id = await a.evaluate(() => document.body.dataset.ready);
    // Every camera's state: shown, the frame it holds, a hash of its pixels.
    const cams = () => a.evaluate(() => [...document.querySelectorAll('#videos img.cam')].map((img) => {
      const r = img.getBoundingClientRect();
      let hash = 0;
      if (img.complete && img.naturalWidth > 0) {
        const c = document.createElement('canvas');
        c.width = img.naturalWidth; c.height = img.naturalHeight;
        const g = c.getContext('2d');
        g.drawImage(img, 0, 0);
        const px = g.getImageData(0, 0, c.width, c.height).data;
        for (let i = 0; i < px.length; i++) hash = (hash * 31 + px[i]) >>> 0;
      }
      return { key: img.dataset.key, frame: img.dataset.frame, w: img.naturalWidth, shown: r.width > 0 && r.height > 0 && !document.getElementById('videos').hidden, hash };
    }));
    const atFrame = (f) => a.waitForFunction((f) => {
      const imgs = [...document.querySelectorAll('#videos img.cam')];
      return imgs.length > 0 && imgs.every((i) => i.dataset.frame === String(f) && i.complete && i.naturalWidth > 0)
        && document.getElementById('scrub').value === String(f);
    }, f, { timeout: 15000 });
    await atFrame(0);
    const c0 = await cams();
    log('image cameras at frame 0', JSON.stringify(c0));
    check(c0.length === 2 && c0.every((c) => c.shown && c.w > 0), `two image cameras shown with a frame: ${JSON.stringify(c0)}`);
    check(c0.map((c) => c.key).join() === 'agentview_image,robot0_eye_in_hand_image', `camera names: ${c0.map((c) => c.key)}`);
    check(await a.evaluate(() => document.querySelectorAll('#videos video').length === 0), 'no video element for image cameras');
    // keyboard stepping: every camera follows
    for (let k = 0; k < 3; k++) await a.keyboard.press('.');
    await atFrame(3);
    const c3 = await cams();
    check(c3.every((c, i) => c.hash !== c0[i].hash), `stepping changed every camera's picture: ${JSON.stringify(c3)}`);
    await a.keyboard.press(',');
    await atFrame(2);
    // scrubbing far: the frames there are fetched on demand
    await a.evaluate(() => { const s = document.getElementById('scrub'); s.value = '200'; s.dispatchEvent(new Event('input')); });
    await atFrame(200);
    const c200 = await cams();
    check(c200.every((c, i) => c.hash !== c3[i].hash && c.hash !== c0[i].hash), `scrubbing changed every camera: ${JSON.stringify(c200)}`);
    // playing advances every camera together (a condition with a timeout, not a fixed sleep)
    await a.keyboard.press(' ');
    const playedOk = await a.waitForFunction(() => {
      const f = Number(document.getElementById('scrub').value);
      const imgs = [...document.querySelectorAll('#videos img.cam')];
      return f >= 205 && imgs.every((i) => Number(i.dataset.frame) >= 203);
    }, null, { timeout: 15000 }).then(() => true, () => false);
    await a.keyboard.press(' ');
    const fp = Number(await a.evaluate(() => document.getElementById('scrub').value));
    await atFrame(fp);
    check(playedOk && fp > 200, `playing advanced the image cameras (frame ${fp})`);
    const shown = await cams();
    await a.evaluate(() => window.scrollTo(0, 0));
    const shotPath = join(OUT, 'robomimic_cameras.png');
    await a.screenshot({ path: shotPath, fullPage: true });
    log('screenshot', shotPath);
    a.off('request', onReq);
    const own = frameReqs.filter((p) => p.includes(`/episodes/${encodeURIComponent(id)}/frames/`));
    log(`image cameras: ${own.length} frame requests for episode ${id} (${frameReqs.length} in all, prefetch included)`);
    result.image_cameras = { episode_id: id, cameras: shown.length, frame: fp, frame_requests: own.length, all_frame_requests: frameReqs.length };
  }

  // ---------------------------------------------------------------- sign out
  await a.click('#signout');
  await a.waitForSelector('#signin:not([hidden])');
  const after = await a.evaluate(async () => (await fetch('/v1/episodes')).status);
  check(after === 401, `signed out: the API answers 401 (got ${after})`);

  check(consoleErrors.length === 0, `no errors in the page console: ${consoleErrors.join(' | ')}`);

  // ---------------------------------------------------------------- the figures
  result.advance_wall_ms = stats(wallMs);
  result.advance_in_page_ms = stats(inPageMs);
  result.keyboard_actions_per_labeled_episode = 3 / 3;
  log('wall-clock verdict key → next episode playable (ms):', JSON.stringify(result.advance_wall_ms));
  log('in-page verdict key → next episode playable (ms):', JSON.stringify(result.advance_in_page_ms));
  log('keyboard actions per labeled episode: 1 (3 keys for 3 episodes; the conflict took 3: s, Tab, Enter)');
  await ctxA.close();
  await ctxB.close();
} finally {
  await browser.close();
}
console.log(`E2E_RESULT ${JSON.stringify(result)}`);
