// The review queue in the labeling page, in headless Chromium: started by
// tests/web_labeling.rs with the Lift rollouts scored by a trained classifier (a `score` job).
// Signs in, picks "verifier uncertain first" in the order selector, checks the queue shows the
// episodes in the API's order with the nearest-0.5 one first, waits for the score plot on the
// timeline, seeks by clicking it and screenshots the view into UFOPS_ARTIFACTS.
//
// Env: UFOPS_URL, UFOPS_TOKEN_A (a labeler), UFOPS_EXPECT (the API's uncertain-first ids, comma
// separated), UFOPS_ARTIFACTS, CHROMIUM. Prints `E2E_RESULT <json>`.

import { chromium } from 'playwright-core';
import { mkdirSync } from 'node:fs';
import { join } from 'node:path';

const URL = process.env.UFOPS_URL;
const TOKEN = process.env.UFOPS_TOKEN_A;
const EXPECT = (process.env.UFOPS_EXPECT || '').split(',').filter(Boolean);
const OUT = process.env.UFOPS_ARTIFACTS || 'artifacts';
const EXE = process.env.CHROMIUM || '/usr/bin/chromium';
if (!URL || !TOKEN || EXPECT.length === 0) {
  console.error('set UFOPS_URL, UFOPS_TOKEN_A and UFOPS_EXPECT');
  process.exit(2);
}
mkdirSync(OUT, { recursive: true });
const check = (cond, msg) => { if (!cond) throw new Error(`check failed: ${msg}`); };

const browser = await chromium.launch({ executablePath: EXE, headless: true, args: ['--no-sandbox', '--disable-dev-shm-usage'] });
try {
  const ctx = await browser.newContext({ viewport: { width: 1440, height: 1100 } });
  const p = await ctx.newPage();
  const errors = [];
  p.on('pageerror', (e) => { errors.push(String(e)); console.error('[page error]', String(e)); });
  p.on('console', (m) => { if (m.type() === 'error') console.error('[console]', m.text()); });
  await p.goto(`${URL}/ui/#policy=bc`);
  await p.waitForSelector('#signin:not([hidden])');
  await p.fill('#token', TOKEN);
  await p.keyboard.press('Enter');
  await p.waitForSelector('#app:not([hidden])');
  await p.waitForFunction(() => document.body.dataset.ready, null, { timeout: 20000 })
    .catch(async (e) => { await p.screenshot({ path: join(OUT, 'review-failed.png'), fullPage: true }); console.error(await p.textContent('#ep-status')); throw e; });
  // The order selector: the queue is listed again in the verifier's order.
  await p.selectOption('#f-order', 'uncertain');
  await p.waitForFunction(() => location.hash.includes('order=uncertain') && document.body.dataset.ready, null, { timeout: 20000 });
  const queue = await p.evaluate(() => window.ufops.state.queue.map((e) => e.id));
  const shown = await p.evaluate(() => document.body.dataset.ready);
  const want = EXPECT;
  check(JSON.stringify(queue) === JSON.stringify(want), `queue ${queue} is the API's uncertain-first order ${want}`);
  check(shown === want[0], `the first episode shown (${shown}) is the one nearest 0.5 (${want[0]})`);
  // The score on the timeline, with the frame cursor moving with the player.
  await p.waitForSelector(`#score-plot[data-scored="${shown}"]`, { timeout: 20000 });
  const over = await p.$('#score-plot .u-over');
  const box = await over.boundingBox();
  await p.mouse.click(box.x + box.width * 0.6, box.y + box.height / 2);
  await p.waitForFunction(() => Number(document.getElementById('frame').textContent.match(/\d+/)?.[0] || 0) > 0, null, { timeout: 5000 })
    .catch(() => {});
  const frame = await p.textContent('#frame');
  const cursor = await p.$eval('#score-plot .frame-cursor', (el) => parseFloat(el.style.left));
  check(cursor > box.width * 0.4, `the score plot's frame cursor followed the seek (left ${cursor}px of ${box.width})`);
  const path = join(OUT, 'review-uncertain-score-timeline.png');
  await p.screenshot({ path, fullPage: true });
  console.log('[e2e] screenshot', path);
  check(errors.length === 0, `page errors: ${errors.join('; ')}`);
  console.log(`E2E_RESULT ${JSON.stringify({ queue, shown, frame, cursor })}`);
} finally {
  await browser.close();
}
