// End-to-end test of the scoreboard page in real headless Chromium (Debian's `chromium`, driven
// by playwright-core). Started by tests/web_labeling.rs (`scoreboard_page_in_headless_chromium`)
// against `ufops serve` with synthetic evaluation runs of policy `synth` ingested.
//
// Env: UFOPS_URL, UFOPS_TOKEN (a viewer), UFOPS_ARTIFACTS (screenshots), CHROMIUM. Prints
// `E2E_RESULT <json>`: the rows as the page shows them, and what its download links return.

import { chromium } from 'playwright-core';
import { mkdirSync } from 'node:fs';
import { join } from 'node:path';

const URL = process.env.UFOPS_URL;
const TOKEN = process.env.UFOPS_TOKEN;
const OUT = process.env.UFOPS_ARTIFACTS || 'artifacts';
const EXE = process.env.CHROMIUM || '/usr/bin/chromium';
if (!URL || !TOKEN) {
  console.error('set UFOPS_URL and UFOPS_TOKEN');
  process.exit(2);
}
mkdirSync(OUT, { recursive: true });
const log = (...a) => console.log('[e2e]', ...a);
function check(cond, msg) {
  if (!cond) throw new Error(`check failed: ${msg}`);
}

const browser = await chromium.launch({ executablePath: EXE, headless: true, args: ['--no-sandbox', '--disable-dev-shm-usage'] });
const result = {};
try {
  // A common laptop window: every column, Δ included, must fit it.
  const ctx = await browser.newContext({ viewport: { width: 1440, height: 900 } });
  const page = await ctx.newPage();
  const errors = [];
  page.on('console', (m) => { if (m.type() === 'error' && !m.text().startsWith('Failed to load resource')) errors.push(m.text()); });
  page.on('pageerror', (e) => errors.push(String(e)));

  // Not signed in: the page says where to sign in.
  await page.goto(`${URL}/ui/scoreboard.html#policy=synth`);
  await page.waitForSelector('#need-signin:not([hidden])');
  // Sign in on the labeling page, then back.
  await page.goto(`${URL}/ui/`);
  await page.waitForSelector('#signin:not([hidden])');
  await page.fill('#token', TOKEN);
  await page.keyboard.press('Enter');
  await page.waitForSelector('#app:not([hidden])');
  await page.goto(`${URL}/ui/scoreboard.html#policy=synth`);
  await page.waitForFunction(() => document.body.dataset.ready && document.body.dataset.ready !== 'error', null, { timeout: 20000 });
  const read = () => page.evaluate(() => ({
    summary: document.getElementById('summary').textContent,
    rows: [...document.querySelectorAll('#rows tbody tr')].map((tr) => ({
      checkpoint: tr.dataset.checkpoint,
      run: tr.dataset.run,
      baseline: tr.classList.contains('baseline'),
      cells: [...tr.children].map((td) => (td.querySelector('.num') || td).textContent),
      bars: tr.querySelectorAll('svg.ci').length,
      bar_width: [...tr.querySelectorAll('svg.ci rect.ci-bar')].map((r) => Number(r.getAttribute('width'))),
      sequential: tr.querySelector('td.sequential .badge')?.dataset.decision ?? null,
      sequential_text: tr.querySelector('td.sequential')?.textContent ?? null,
    })),
    aliases: [...document.querySelectorAll('#aliases-list li')].map((li) => ({ alias: li.dataset.alias, text: li.textContent })),
    csv: document.getElementById('dl-csv').getAttribute('href'),
    calibration: [...document.querySelectorAll('#verifiers svg.reliability')].map((s) => ({
      artifact: s.dataset.artifact, points: s.querySelectorAll('circle').length,
    })),
    json: document.getElementById('dl-json').getAttribute('href'),
    monitors: [...document.querySelectorAll('#rows td.verifier .monitor')].map((m) => ({ id: m.dataset.monitor, text: m.textContent })),
    sensitivity: [...document.querySelectorAll('#rows td.verifier .sensitivity')].map((m) => ({ flagged: m.dataset.flagged, text: m.textContent })),
  }));
  const first = await read();
  log('rows', first.rows.length, first.summary);
  check(first.rows.length >= 4, `rows drawn: ${first.rows.length}`);
  check(first.calibration.length >= 1 && first.calibration.every((c) => c.points > 0), `a reliability diagram: ${JSON.stringify(first.calibration)}`);
  check(first.rows.every((r) => r.bars >= 1 && r.bar_width.every((w) => w > 0)), 'every row has its interval bar');
  check(first.rows.filter((r) => !r.baseline && r.run !== '-').every((r) => r.bars === 2) , 'compared rows have a Δ bar');
  // Every row compared with a baseline has its sequential-test badge (decided, or how many more).
  check(first.rows.filter((r) => r.bars === 2).every((r) => r.sequential && r.sequential !== 'error'), `sequential badges: ${JSON.stringify(first.rows.map((r) => r.sequential_text))}`);
  check(first.aliases.length >= 1, 'the aliases panel lists the policy\'s aliases');
  // The Δ column (header, numbers and bars) ends inside the window and inside the table's panel
  // (which scrolls sideways rather than overflow the page): nothing of it is cut off.
  const fit = await page.evaluate(() => {
    const panel = document.getElementById('rows').closest('.panel');
    const edge = Math.min(document.documentElement.clientWidth, panel.getBoundingClientRect().right);
    const th = [...document.querySelectorAll('#rows thead th')].find((h) => h.textContent.startsWith('Δ'));
    const cells = [th, ...document.querySelectorAll('#rows td.diff')];
    return { edge, window: window.innerWidth, right: Math.max(...cells.map((c) => c.getBoundingClientRect().right)),
      cells: cells.length, scrolled: panel.scrollLeft, table: panel.scrollWidth, panel: panel.clientWidth };
  });
  log('Δ column', JSON.stringify(fit));
  check(fit.window === 1440 && fit.cells > 1 && fit.scrolled === 0, `measured at 1440 px: ${JSON.stringify(fit)}`);
  check(fit.right <= fit.edge, `the Δ column's right edge (${fit.right}px) lies within the view (${fit.edge}px)`);
  // And these rows' every column fits: the panel need not scroll sideways at 1440 px.
  check(fit.table <= fit.panel, `the table (${fit.table}px) fits its panel (${fit.panel}px) at 1440 px`);
  await page.screenshot({ path: join(OUT, 'scoreboard.png'), fullPage: true });
  log('screenshot', join(OUT, 'scoreboard.png'));
  // The download links return the same query as CSV and JSON (with the session cookie).
  const dl = await page.evaluate(async ({ csv, json }) => {
    const c = await fetch(csv, { credentials: 'same-origin' });
    const j = await fetch(json, { credentials: 'same-origin' });
    return { csv_type: c.headers.get('content-type'), csv: await c.text(), json_rows: (await j.json()).rows.length };
  }, first);
  check(dl.csv_type.startsWith('text/csv'), `CSV content type ${dl.csv_type}`);
  check(dl.csv.trim().split('\n').length === first.rows.length + 1, 'CSV: a header and one line per row');
  check(dl.json_rows === first.rows.length, 'JSON: the same rows');
  // Another baseline: every row against c1's c-bon10 run.
  await page.selectOption('#f-baseline', 'c-bon10');
  await page.waitForFunction(() => document.body.dataset.ready && window.ufopsScoreboard.baseline === 'c-bon10');
  await page.selectOption('#f-baseline-checkpoint', 'c1');
  await page.waitForFunction(() => document.body.dataset.ready && window.ufopsScoreboard.baseline_checkpoint === 'c1');
  const second = await read();
  check(second.rows.filter((r) => r.baseline).length === 1, 'one baseline row');
  check(/baseline=c-bon10/.test(second.csv) && /baseline_checkpoint=c1/.test(second.csv), `the CSV link follows: ${second.csv}`);
  await page.screenshot({ path: join(OUT, 'scoreboard-baseline-c-bon10.png'), fullPage: true });
  check(errors.length === 0, `no page errors: ${errors.join('; ')}`);
  Object.assign(result, { first, second, download: { csv_lines: dl.csv.trim().split('\n').length, json_rows: dl.json_rows } });
} finally {
  await browser.close();
}
console.log(`E2E_RESULT ${JSON.stringify(result)}`);
