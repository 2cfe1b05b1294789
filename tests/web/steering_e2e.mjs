// Steering telemetry on the labeling page, in headless Chromium: started by tests/steering_page.rs
// with a steered run whose best-of-N steps were logged. For each episode named in UFOPS_EXPECT
// ({episode id: [logged steps]}), opens it and checks the steering plot under the verifier score:
// shown with one record per logged step (hidden for an unsteered episode), the chosen score drawn
// at exactly those steps, and a click near the last one seeks there; then screenshots UFOPS_SHOT.
//
// Env: UFOPS_URL, UFOPS_TOKEN_A (a labeler), UFOPS_EXPECT, UFOPS_SHOT, UFOPS_ARTIFACTS, CHROMIUM.
// Prints `E2E_RESULT <json>`.

import { chromium } from 'playwright-core';
import { mkdirSync } from 'node:fs';
import { join } from 'node:path';

const URL = process.env.UFOPS_URL;
const TOKEN = process.env.UFOPS_TOKEN_A;
const EXPECT = JSON.parse(process.env.UFOPS_EXPECT || '{}');
const SHOT = process.env.UFOPS_SHOT || '';
const OUT = process.env.UFOPS_ARTIFACTS || 'artifacts';
const EXE = process.env.CHROMIUM || '/usr/bin/chromium';
if (!URL || !TOKEN || Object.keys(EXPECT).length === 0) {
  console.error('set UFOPS_URL, UFOPS_TOKEN_A and UFOPS_EXPECT');
  process.exit(2);
}
mkdirSync(OUT, { recursive: true });
const check = (cond, msg) => { if (!cond) throw new Error(`check failed: ${msg}`); };

const browser = await chromium.launch({ executablePath: EXE, headless: true, args: ['--no-sandbox', '--disable-dev-shm-usage'] });
const result = {};
try {
  const ctx = await browser.newContext({ viewport: { width: 1440, height: 1100 } });
  const p = await ctx.newPage();
  const errors = [];
  p.on('pageerror', (e) => { errors.push(String(e)); console.error('[page error]', String(e)); });
  p.on('console', (m) => { if (m.type() === 'error') console.error('[console]', m.text()); });
  await p.goto(`${URL}/ui/`);
  await p.waitForSelector('#signin:not([hidden])');
  await p.fill('#token', TOKEN);
  await p.keyboard.press('Enter');
  await p.waitForSelector('#app:not([hidden])');
  for (const [id, want] of Object.entries(EXPECT)) {
    await p.goto(`${URL}/ui/#ep=${id}`);
    await p.reload();
    await p.waitForFunction((id) => document.body.dataset.ready === id, id, { timeout: 20000 })
      .catch(async (e) => { await p.screenshot({ path: join(OUT, 'steering-failed.png'), fullPage: true }); throw e; });
    const plot = await p.$eval('#steering-plot', (el) => ({ hidden: el.hidden, steps: Number(el.dataset.steps || 0), title: el.querySelector('.u-title')?.textContent || '' }));
    if (want.length === 0) {
      check(plot.hidden, `${id}: no steering plot for an unsteered episode`);
      result[id] = { shown: false };
      continue;
    }
    check(!plot.hidden, `${id}: the steering plot is shown`);
    check(plot.steps === want.length, `${id}: ${plot.steps} records drawn, ${want.length} logged`);
    check(plot.title.includes(`best-of-N: ${want.length} steps, N = 8`), `${id}: title ${JSON.stringify(plot.title)}`);
    // The records are drawn at exactly the logged steps.
    const logged = await p.$eval('#steering-plot', (el) => el.dataset.logged || '');
    check(logged === want.join(','), `${id}: drawn at steps ${logged}, logged at ${want.join(',')}`);
    // Click at the last logged step: the scrub bar moves there.
    const last = want[want.length - 1];
    const box = await p.$eval('#steering-plot .u-over', (el) => { const r = el.getBoundingClientRect(); return { x: r.x, y: r.y, w: r.width, h: r.height }; });
    const n = Number(await p.$eval('#scrub', (el) => el.max)) + 1;
    await p.mouse.click(box.x + (box.w * last) / Math.max(1, n - 1), box.y + box.h / 2);
    await p.waitForFunction((s) => Math.abs(Number(document.getElementById('scrub').value) - s) <= 1, last, { timeout: 5000 });
    const seeked = Number(await p.$eval('#scrub', (el) => el.value));
    result[id] = { shown: true, steps: plot.steps, title: plot.title, seeked };
    if (id === SHOT) {
      const path = join(OUT, 'steering_timeline.png');
      await p.screenshot({ path, fullPage: true });
      console.log('[e2e] screenshot', path);
    }
  }
  check(errors.length === 0, `page errors: ${errors.join('; ')}`);
  console.log(`E2E_RESULT ${JSON.stringify(result)}`);
} finally {
  await browser.close();
}
