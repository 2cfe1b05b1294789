// Human takeovers on the labeling page's timeline, in headless Chromium:
// started by tests/takeovers.rs with a generated LeRobot v3.0 DAgger rollout dataset ingested.
// For each episode named in UFOPS_EXPECT, opens it, checks the strip under the scrub bar shows one
// shaded span per run of `intervention` steps (and none for an episode without takeovers), that
// clicking a span seeks to its first step, and that the metadata names the first takeover; then
// screenshots the episode with two takeovers into UFOPS_ARTIFACTS.
//
// Env: UFOPS_URL, UFOPS_TOKEN_A (a labeler), UFOPS_EXPECT (JSON {episode id: [[start, end], …]}),
// UFOPS_SHOT (the id to screenshot), UFOPS_ARTIFACTS, CHROMIUM. Prints `E2E_RESULT <json>`.

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
  const ctx = await browser.newContext({ viewport: { width: 1440, height: 1000 } });
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
    await p.reload(); // a hash change alone does not load the page again
    await p.waitForFunction((id) => document.body.dataset.ready === id, id, { timeout: 20000 })
      .catch(async (e) => { await p.screenshot({ path: join(OUT, 'takeovers-failed.png'), fullPage: true }); throw e; });
    const strip = await p.$eval('#takeovers', (el) => ({
      hidden: el.hidden,
      spans: [...el.querySelectorAll('.span.takeover')].map((s) => [Number(s.dataset.start), Number(s.dataset.end)]),
      legend: el.querySelector('.legend')?.textContent || '',
      width: el.getBoundingClientRect().width,
      scrubWidth: document.getElementById('scrub').getBoundingClientRect().width,
    }));
    check(!strip.hidden, `${id}: the takeover strip is shown for an episode with an intervention column`);
    check(JSON.stringify(strip.spans) === JSON.stringify(want), `${id}: spans ${JSON.stringify(strip.spans)} are the takeovers ${JSON.stringify(want)}`);
    check(Math.abs(strip.width - strip.scrubWidth) < 2, `${id}: the strip (${strip.width}px) is as wide as the scrub bar (${strip.scrubWidth}px)`);
    const meta = await p.$$eval('#meta tr', (rows) => rows.map((r) => r.textContent));
    const row = meta.find((r) => r.startsWith('human takeover')) || '';
    check(want.length ? row.includes(`from step ${want[0][0]}`) : row.includes('none'), `${id}: the metadata row ${JSON.stringify(row)}`);
    let seeked = null;
    if (want.length) {
      // Clicking the last span seeks to its first step; the strip's cursor follows.
      const last = (await p.$$('#takeovers .span.takeover')).pop();
      await last.click();
      const start = want[want.length - 1][0];
      await p.waitForFunction((s) => Number(document.getElementById('scrub').value) === s, start, { timeout: 5000 });
      seeked = Number(await p.$eval('#scrub', (el) => el.value));
      const n = Number(await p.$eval('#scrub', (el) => el.max)) + 1;
      const cursor = parseFloat(await p.$eval('#takeovers .cursor', (el) => el.style.left));
      check(Math.abs(cursor - (100 * start) / n) < 1e-6, `${id}: the strip's cursor is at step ${start} (${cursor}% of ${n} steps)`);
    }
    result[id] = { spans: strip.spans, legend: strip.legend, meta: row, seeked };
    if (id === SHOT) {
      const path = join(OUT, 'takeovers_timeline.png');
      await p.screenshot({ path, fullPage: true });
      console.log('[e2e] screenshot', path);
    }
  }
  check(errors.length === 0, `page errors: ${errors.join('; ')}`);
  console.log(`E2E_RESULT ${JSON.stringify(result)}`);
} finally {
  await browser.close();
}
