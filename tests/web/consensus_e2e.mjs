// Several labelers in real headless Chromium. Started by
// tests/web_labeling.rs against `ufops serve` with six synthetic episodes of policy `synth`, all
// unknown, in a blind campaign that needs two labelers, with failure causes for every task.
//
// Alice labels four episodes with the keyboard (one failure with a cause key and a time span);
// Bob then sees on the page and through the API that one labeler voted but not what, labels the
// same four and disagrees once; the admin settles the dispute from the adjudication list. κ from
// the API and on the page must equal κ computed here from the verdicts the keys gave.
//
// Env: UFOPS_URL, UFOPS_TOKEN_A / UFOPS_TOKEN_B (labelers), UFOPS_TOKEN_ADMIN, UFOPS_ARTIFACTS,
// CHROMIUM. Prints `E2E_RESULT <json>` for the Rust test to check through the API.

import { chromium } from 'playwright-core';
import { mkdirSync } from 'node:fs';
import { join } from 'node:path';

const URL = process.env.UFOPS_URL;
const TOKENS = { alice: process.env.UFOPS_TOKEN_A, bob: process.env.UFOPS_TOKEN_B, admin: process.env.UFOPS_TOKEN_ADMIN };
const OUT = process.env.UFOPS_ARTIFACTS || 'artifacts';
const EXE = process.env.CHROMIUM || '/usr/bin/chromium';
if (!URL || !TOKENS.alice || !TOKENS.bob || !TOKENS.admin) {
  console.error('set UFOPS_URL, UFOPS_TOKEN_A, UFOPS_TOKEN_B and UFOPS_TOKEN_ADMIN');
  process.exit(2);
}
mkdirSync(OUT, { recursive: true });
const log = (...a) => console.log('[consensus-e2e]', ...a);
function check(cond, msg) {
  if (!cond) throw new Error(`check failed: ${msg}`);
}
const shot = async (page, name) => page.screenshot({ path: join(OUT, `${name}.png`), fullPage: true });
const LABEL = { s: 'success', f: 'failure' };

/** Cohen's κ from two raters' verdicts on the same episodes, written out here. */
function kappa(a, b) {
  const ids = Object.keys(a).filter((id) => id in b);
  const n = ids.length;
  const po = ids.filter((id) => a[id] === b[id]).length / n;
  let pe = 0;
  for (const c of ['success', 'failure', 'unknown']) {
    pe += (ids.filter((id) => a[id] === c).length / n) * (ids.filter((id) => b[id] === c).length / n);
  }
  return (po - pe) / (1 - pe);
}

const browser = await chromium.launch({ executablePath: EXE, headless: true, args: ['--no-sandbox', '--disable-dev-shm-usage'] });
const errors = [];
async function signIn(who) {
  const ctx = await browser.newContext({ viewport: { width: 1440, height: 1000 } });
  const page = await ctx.newPage();
  page.on('console', (m) => { if (m.type() === 'error' && !m.text().startsWith('Failed to load resource')) errors.push(`${who}: ${m.text()}`); });
  page.on('pageerror', (e) => errors.push(`${who}: ${e}`));
  await page.goto(`${URL}/ui/#policy=synth`);
  await page.waitForSelector('#signin:not([hidden])');
  await page.fill('#token', TOKENS[who]);
  await page.keyboard.press('Enter');
  await page.waitForSelector('#app:not([hidden])');
  await page.waitForFunction(() => document.body.dataset.ready, null, { timeout: 20000 });
  return page;
}
const apiGet = (page, path) => page.evaluate(async (p) => {
  const r = await fetch(p, { headers: { 'X-Ufops-UI': '1' } });
  return { status: r.status, body: await r.json() };
}, path);

/** Presses `keys` on the episode on screen; the last key is the verdict, which auto-advances. */
async function verdict(page, keys) {
  const id = await page.evaluate(() => document.body.dataset.ready);
  for (const k of keys.slice(0, -1)) await page.keyboard.press(k);
  await page.keyboard.press(keys[keys.length - 1]);
  // '' while the next episode loads: wait for it to be shown.
  await page.waitForFunction((prev) => { const r = document.body.dataset.ready; return r && r !== prev; }, id, { timeout: 15000 });
  return id;
}
async function settled(page) {
  await page.waitForFunction(() => window.ufops.state.queue.every((e) => !e.pending), null, { timeout: 15000 });
}

const result = { alice: {}, bob: {} };
try {
  // ---------------------------------------------------------------- alice: four verdicts
  const a = await signIn('alice');
  await a.waitForFunction(() => document.getElementById('campaign').textContent.includes('2 labelers must agree, blind'));
  await a.waitForFunction(() => document.querySelectorAll('#causes li[data-cause]').length === 3);
  const planA = [['s'], ['f'], ['s'], ['2', '[', '.', '.', '.', ']', 'f']];
  for (const keys of planA) {
    if (keys.length > 1) {
      // the cause and span show before the verdict is given
      for (const k of keys.slice(0, -1)) await a.keyboard.press(k);
      const shown = await a.evaluate(() => ({
        cause: document.querySelector('#causes li.chosen')?.dataset.cause,
        span: document.querySelector('#spans li[data-span]')?.dataset.span,
      }));
      check(shown.cause === 'collision' && shown.span === '0-3', `cause and span on the page: ${JSON.stringify(shown)}`);
      await shot(a, 'consensus-01-cause-and-span');
      const id = await verdict(a, [keys[keys.length - 1]]);
      result.alice[id] = LABEL.f;
      result.span_episode = id;
    } else {
      result.alice[await verdict(a, keys)] = LABEL[keys[0]];
    }
  }
  await settled(a);
  check(Object.keys(result.alice).length === 4, `four different episodes: ${JSON.stringify(result.alice)}`);
  const ids = Object.keys(result.alice);
  // labels stay unknown: one labeler of two has voted
  for (const id of ids) {
    const v = await apiGet(a, `/v1/episodes/${id}/votes`);
    check(v.status === 200 && v.body.state === 'pending' && v.body.voters === 1, `pending after alice: ${JSON.stringify(v.body)}`);
  }
  const span = await apiGet(a, `/v1/episodes/${result.span_episode}/votes`);
  check(span.body.votes[0].failure_cause === 'collision' && span.body.votes[0].spans[0].end_step === 3, `the vote carries its cause and span: ${JSON.stringify(span.body)}`);

  // ---------------------------------------------------------------- bob: blind, then four verdicts
  const b = await signIn('bob');
  const first = await b.evaluate(() => document.body.dataset.ready);
  check(first === ids[0], `bob starts on the first episode alice labeled (${first} vs ${ids[0]})`);
  await b.waitForSelector('#votes-hidden');
  const hiddenText = await b.textContent('#votes-hidden');
  check(hiddenText.startsWith('1 verdict hidden'), `blind on the page: ${hiddenText}`);
  const before = await apiGet(b, `/v1/episodes/${first}/votes`);
  check(before.body.hidden === true && before.body.votes.length === 0 && before.body.voters === 1, `blind in the API: ${JSON.stringify(before.body)}`);
  await shot(b, 'consensus-02-bob-blind');
  // bob disagrees on alice's second success
  const planB = { [ids[0]]: 's', [ids[1]]: 'f', [ids[2]]: 'f', [ids[3]]: 'f' };
  for (let k = 0; k < 4; k++) {
    const on = await b.evaluate(() => document.body.dataset.ready);
    check(on in planB, `bob is on one of alice's episodes (${on})`);
    result.bob[await verdict(b, [planB[on]])] = LABEL[planB[on]];
  }
  await settled(b);
  const after = await apiGet(b, `/v1/episodes/${first}/votes`);
  check(after.body.hidden === false && after.body.votes.length === 2, `after voting bob sees both: ${JSON.stringify(after.body)}`);
  const disputed = ids.filter((id) => result.alice[id] !== result.bob[id]);
  check(disputed.length === 1, `one disagreement: ${disputed}`);
  result.disputed = disputed[0];

  // ---------------------------------------------------------------- admin settles it
  const adm = await signIn('admin');
  await adm.waitForFunction((id) => document.querySelector(`#adjudication li[data-episode="${id}"]`), result.disputed, { timeout: 15000 });
  const listed = await adm.evaluate(() => [...document.querySelectorAll('#adjudication li[data-episode]')].map((li) => li.dataset.episode));
  check(listed.length === 1 && listed[0] === result.disputed, `the adjudication list: ${listed}`);
  await shot(adm, 'consensus-03-adjudication');
  await adm.click(`#adjudication button[data-settle="failure"][data-episode="${result.disputed}"]`);
  await adm.waitForFunction(() => !document.querySelector('#adjudication li[data-episode]'), null, { timeout: 15000 });
  check((await adm.textContent('#adjudication-status')).includes('settled: failure'), 'settled on the page');
  const q = await apiGet(adm, '/v1/adjudication?policy=synth');
  check(q.status === 200 && q.body.length === 0, `queue empty: ${JSON.stringify(q.body)}`);

  // ---------------------------------------------------------------- κ: API, page, here
  const ag = await apiGet(adm, '/v1/agreement?policy=synth');
  const pair = ag.body.pairs.find((p) => p.a === 'alice' && p.b === 'bob');
  result.kappa_independent = kappa(result.alice, result.bob);
  result.kappa_api = pair.kappa;
  await adm.waitForFunction(() => document.querySelector('#agreement tr.pair') && document.getElementById('agreement').textContent.includes('1 settled'));
  result.kappa_page = Number(await adm.getAttribute('#agreement tr.pair', 'data-kappa'));
  check(Math.abs(result.kappa_api - result.kappa_independent) < 1e-12, `κ API ${result.kappa_api} vs here ${result.kappa_independent}`);
  check(Math.abs(result.kappa_page - result.kappa_independent) < 1e-12, `κ page ${result.kappa_page} vs here ${result.kappa_independent}`);
  result.agreement = ag.body;
  await shot(adm, 'consensus-04-agreement');
  check(errors.length === 0, `no page errors: ${errors.join(' | ')}`);
  console.log(`E2E_RESULT ${JSON.stringify(result)}`);
} finally {
  await browser.close();
}
