// The review queue in the labeling page, in headless Chromium: started by
// tests/web_labeling.rs with the Lift rollouts scored by a trained classifier (a `score` job).
// Signs in, picks "verifier uncertain first" in the order selector, checks the queue shows the
// episodes in the API's order with the nearest-0.5 one first, waits for the score plot on the
// timeline, seeks by clicking it and screenshots the view into UFOPS_ARTIFACTS.
// With UFOPS_UNSCORED=1 (before the score job): the same order on `bc` (a classifier, no scores
// yet) and on `lift-new` (no classifier) must say there are no scores and give the commands that
// store them, in a 1440x900 window (screenshot `review-no-scores.png`).
//
// Env: UFOPS_URL, UFOPS_TOKEN_A (a labeler), UFOPS_EXPECT (the API's uncertain-first ids, comma
// separated), UFOPS_UNSCORED, UFOPS_ARTIFACTS, CHROMIUM. Prints `E2E_RESULT <json>`.

import { chromium } from 'playwright-core';
import { mkdirSync } from 'node:fs';
import { join } from 'node:path';

const URL = process.env.UFOPS_URL;
const TOKEN = process.env.UFOPS_TOKEN_A;
const EXPECT = (process.env.UFOPS_EXPECT || '').split(',').filter(Boolean);
const UNSCORED = process.env.UFOPS_UNSCORED === '1';
const OUT = process.env.UFOPS_ARTIFACTS || 'artifacts';
const EXE = process.env.CHROMIUM || '/usr/bin/chromium';
if (!URL || !TOKEN || (EXPECT.length === 0 && !UNSCORED)) {
  console.error('set UFOPS_URL, UFOPS_TOKEN_A and UFOPS_EXPECT (or UFOPS_UNSCORED=1)');
  process.exit(2);
}
mkdirSync(OUT, { recursive: true });
const check = (cond, msg) => { if (!cond) throw new Error(`check failed: ${msg}`); };

/** The queue's notice about scores: shown or not, its kind and text. */
const notice = (p) => p.$eval('#review-notice', (n) => ({ hidden: n.hidden, state: n.dataset.state || null,
  // its commands as one line each (they are shown with shell line continuations)
  text: n.textContent.replace(/\\\n\s*/g, '') }));

const browser = await chromium.launch({ executablePath: EXE, headless: true, args: ['--no-sandbox', '--disable-dev-shm-usage'] });
if (UNSCORED) {
  try {
    const ctx = await browser.newContext({ viewport: { width: 1440, height: 900 } });
    const p = await ctx.newPage();
    const errors = [];
    p.on('pageerror', (e) => { errors.push(String(e)); console.error('[page error]', String(e)); });
    await p.goto(`${URL}/ui/#policy=bc&order=uncertain`);
    await p.waitForSelector('#signin:not([hidden])');
    await p.fill('#token', TOKEN);
    await p.keyboard.press('Enter');
    await p.waitForSelector('#app:not([hidden])');
    // bc/e600 has a classifier but no score job ran: the score command, and the queue by id.
    await p.waitForSelector('#review-notice:not([hidden])', { timeout: 20000 })
      .catch(async (e) => { await p.screenshot({ path: join(OUT, 'review-failed.png'), fullPage: true }); throw e; });
    const bc = await notice(p);
    check(bc.state === 'unscored', `bc's notice is about a missing score job: ${JSON.stringify(bc)}`);
    check(bc.text.includes('No verifier scores yet') && bc.text.includes('ufops review score --policy bc --checkpoint e600'),
      `bc's notice gives the score command: ${bc.text}`);
    const queue = await p.evaluate(() => window.ufops.state.queue.map((e) => e.id));
    check(JSON.stringify(queue) === JSON.stringify([...queue].sort()), `unscored: the queue is in id order: ${queue}`);
    const box = await p.$eval('#review-notice', (n) => { const r = n.getBoundingClientRect(); return { top: r.top, bottom: r.bottom }; });
    check(box.top >= 0 && box.bottom <= 900, `the notice is in view without scrolling: ${JSON.stringify(box)}`);
    const path = join(OUT, 'review-no-scores.png');
    await p.screenshot({ path });
    console.log('[e2e] screenshot', path);
    // lift-new has no classifier at all: train one first, then score.
    await p.selectOption('#f-policy', 'lift-new');
    await p.waitForSelector('#review-notice[data-state="no-verifier"]', { timeout: 20000 });
    const fresh = await notice(p);
    check(fresh.text.includes('ufops split create --policy lift-new --checkpoint e0')
      && fresh.text.includes('ufops review score --policy lift-new --checkpoint e0'), `lift-new's notice: ${fresh.text}`);
    await p.screenshot({ path: join(OUT, 'review-no-verifier.png') });
    // The id order needs no scores: no notice.
    await p.selectOption('#f-order', '');
    await p.waitForFunction(() => document.getElementById('review-notice').hidden, null, { timeout: 20000 });
    check(errors.length === 0, `page errors: ${errors.join('; ')}`);
    console.log(`E2E_RESULT ${JSON.stringify({ bc, fresh, queue })}`);
  } finally {
    await browser.close();
  }
  process.exit(0);
}
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
  const scored = await notice(p);
  check(scored.hidden, `scored: no notice about missing scores (${scored.text})`);
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
