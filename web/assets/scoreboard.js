// The scoreboard page: GET /v1/scoreboard for a policy (and a baseline run), drawn as a table with
// small SVG interval bars, each row's anytime-valid comparison with its baseline as a badge
// (GET /v1/compare), the policy's aliases with their evidence, and the same query's CSV and JSON as
// download links. It only reads.

import { call, ApiError } from './api.js';
import { $, el } from './dom.js';

const SVG = 'http://www.w3.org/2000/svg';
const W = 160;
const H = 16;

const q = (params) => {
  const u = new URLSearchParams();
  for (const [k, v] of Object.entries(params)) if (v !== undefined && v !== null && v !== '') u.set(k, v);
  return u.toString();
};

function svg(tag, attrs) {
  const e = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
  return e;
}

/** A bar of [lo, hi] with a point at x on the axis [min, max]; a zero line when 0 is inside. */
function intervalBar(lo, hi, x, min, max, color, title) {
  const s = svg('svg', { width: W, height: H, viewBox: `0 0 ${W} ${H}`, class: 'ci' });
  const px = (v) => 4 + ((v - min) / (max - min)) * (W - 8);
  s.appendChild(svg('line', { x1: 4, x2: W - 4, y1: H / 2, y2: H / 2, stroke: '#e5e7eb', 'stroke-width': 1 }));
  if (min < 0 && max > 0) s.appendChild(svg('line', { x1: px(0), x2: px(0), y1: 1, y2: H - 1, stroke: '#9ca3af', 'stroke-width': 1 }));
  s.appendChild(svg('rect', { x: px(lo), y: 4, width: Math.max(1, px(hi) - px(lo)), height: H - 8, fill: color, 'fill-opacity': 0.35, class: 'ci-bar' }));
  s.appendChild(svg('circle', { cx: px(x), cy: H / 2, r: 3, fill: color, class: 'ci-point' }));
  const t = svg('title', {});
  t.textContent = title;
  s.appendChild(t);
  return s;
}

const pct = (x) => (100 * x).toFixed(1);
const pp = (x) => `${x >= 0 ? '+' : ''}${(100 * x).toFixed(1)}`;

function render(sb) {
  const body = $('rows').querySelector('tbody');
  body.replaceChildren();
  const badges = [];
  for (const r of sb.rows) {
    const tr = el('tr', { 'data-run': r.run_name, 'data-checkpoint': r.checkpoint });
    if (r.is_baseline) tr.classList.add('baseline');
    const run = r.run;
    const tags = run && run.tags.length ? ` (${run.tags.join(', ')})` : '';
    const steering = !run ? '-' : run.steering.method === 'bon' ? `bon:${run.steering.n}`
      : run.steering.method === 'base' ? 'base' : `${run.steering.method}:${run.steering.lambda}`;
    const labeled = r.successes + r.failures;
    for (const text of [r.checkpoint, r.task || '-', r.run_name + tags, steering, (run && run.artifact_id) || '-',
      `${r.successes}/${labeled}`]) tr.appendChild(el('td', {}, text));
    const rateTd = el('td', { class: 'rate' });
    const rate = rateTd.appendChild(el('div', { class: 'cell' }));
    if (r.rate !== null) {
      rate.appendChild(el('span', { class: 'num' }, `${pct(r.rate)}% [${pct(r.wilson_95[0])}, ${pct(r.wilson_95[1])}]`));
      rate.appendChild(intervalBar(r.wilson_95[0], r.wilson_95[1], r.rate, 0, 1, '#2563eb', `Wilson 95%: ${pct(r.wilson_95[0])}–${pct(r.wilson_95[1])}%`));
    } else rate.textContent = 'no labels';
    tr.appendChild(rateTd);
    tr.appendChild(el('td', {}, String(r.unlabeled)));
    const dTd = el('td', { class: 'diff' });
    const d = dTd.appendChild(el('div', { class: 'cell' }));
    const b = r.baseline;
    if (b) {
      const [lo, hi] = b.newcombe_95;
      const color = lo > 0 ? '#16a34a' : hi < 0 ? '#dc2626' : '#6b7280';
      d.appendChild(el('span', { class: 'num' }, `${pp(b.diff)} pp [${pp(lo)}, ${pp(hi)}]`));
      d.appendChild(intervalBar(lo, hi, b.diff, -1, 1, color, `vs ${b.checkpoint}/${b.run_name}: Newcombe 95% ${pp(lo)} to ${pp(hi)} pp`));
    } else d.textContent = r.is_baseline ? 'baseline' : '-';
    tr.appendChild(dTd);
    const seq = tr.appendChild(el('td', { class: 'sequential' }, b ? '…' : '-'));
    if (b) badges.push({ td: seq, row: r, base: b });
    tr.appendChild(el('td', {}, b ? (b.rollouts_to_separate ?? '-').toString() : '-'));
    tr.appendChild(el('td', {}, b ? (b.unlabeled_to_flip ?? 'none').toString() : '-'));
    const vq = r.verifier_quality;
    const num = (x) => (typeof x === 'number' ? x.toFixed(3) : '-');
    const vTd = tr.appendChild(el('td', { class: 'verifier' }, vq ? `${num(vq.auroc)} / ${num(vq.ece)}` : '-'));
    if (vq && typeof vq.action_auroc === 'number') vTd.appendChild(sensitivityLine(vq));
    if (vq && vq.monitor) vTd.appendChild(monitorLine(vq.monitor));
    body.appendChild(tr);
  }
  renderVerifiers(sb);
  return badges;
}

/** How much the action chunk matters to the verifier, in one line: its AUROC among held-out
 * samples its observation-only twin scores alike, and the twin's own AUROC (what the trainer
 * measured). A verifier flagged as unlikely to steer well says so. */
function sensitivityLine(vq) {
  const n = (x) => (typeof x === 'number' ? x.toFixed(3) : '-');
  const flagged = vq.steering_flagged === true;
  return el('div', { class: `sensitivity${flagged ? ' flagged' : ''}`, 'data-flagged': String(flagged),
    title: flagged ? vq.steering_warning : 'action: AUROC of the verifier\'s score in excess of its observation-only ' +
      'twin\'s, among held-out samples the twin scores alike (0.5: the chunk adds nothing); obs-only: the twin\'s AUROC' },
    `action ${n(vq.action_auroc)} · obs-only ${n(vq.obs_only_auroc)}${flagged ? ' · ⚠ unlikely to steer well' : ''}`);
}

/** A verifier's failure monitor in one line: its α, the false-alarm rate it showed on held-out
 * successes and the share of failures it caught (what `ufops monitor calibrate` measured). */
function monitorLine(m) {
  const p = (x) => (typeof x === 'number' ? `${(100 * x).toFixed(1)}%` : '-');
  const fa = m.false_alarm_interval ? ` [${p(m.false_alarm_interval[0])}, ${p(m.false_alarm_interval[1])}]` : '';
  return el('div', { class: 'monitor', 'data-monitor': m.id,
    title: `monitor ${m.id}: false alarms on ${m.successes} held-out successes${fa} (Wilson 95%), ` +
      `${m.failures} failures, median lead ${m.lead_steps_median ?? '-'} steps` },
    `alarm α ${m.alpha}: false ${p(m.false_alarm_rate)} · caught ${p(m.detection_rate)}`);
}

/** The anytime-valid comparison of a row with its baseline (GET /v1/compare): a badge saying
 * whether it is decided (and after how many rollouts) or how many more it needs at these rates. */
async function fillBadge({ td, row, base }, sb) {
  const params = { policy: sb.policy, a: `${base.checkpoint}/${base.run_name}`, b: `${row.checkpoint}/${row.run_name}`, version: sb.version, task: row.task || '' };
  try {
    const c = await call('GET', `/v1/compare?${q(params)}`);
    const s = row.task ? (c.tasks.find((t) => t.task === row.task) || c.pooled) : c.pooled;
    const decided = s.decision !== 'undecided';
    const text = decided
      ? `${s.decision.replaceAll('_', ' ')} after ${2 * s.decided_at_pairs} rollouts`
      : s.more_pairs !== null ? `undecided · ~${2 * s.more_pairs} more` : 'undecided';
    const badge = el('span', { class: `badge ${decided ? s.decision : 'undecided'}`, 'data-decision': s.decision,
      title: `${c.method}; ${s.pairs} pairs (${c.pairing}); confidence sequence of Δ [${pp(s.confidence_sequence[0])}, ${pp(s.confidence_sequence[1])}] pp at alpha ${s.alpha}` }, text);
    td.replaceChildren(badge);
  } catch (e) {
    td.replaceChildren(el('span', { class: 'badge error', 'data-decision': 'error' }, e instanceof ApiError ? e.message : String(e)));
  }
}

/** The policy's aliases (`prod`) and the evidence of their last move. */
async function renderAliases(policy) {
  const list = $('aliases-list');
  list.replaceChildren();
  const aliases = await call('GET', `/v1/policies/${encodeURIComponent(policy)}/aliases`);
  for (const a of aliases) {
    const ev = a.evidence;
    const why = ev ? `${ev.gate.replaceAll('_', ' ')} against ${ev.a.checkpoint}${ev.a.run ? '/' + ev.a.run : ''} at version ${ev.version} (${ev.pooled.pairs} pairs, Δ [${pp(ev.pooled.confidence_sequence[0])}, ${pp(ev.pooled.confidence_sequence[1])}] pp)`
      : 'no comparison (first or unprotected move)';
    list.appendChild(el('li', { 'data-alias': a.alias }, `${a.alias} → ${a.target}${a.protected ? ' (protected)' : ''} · moved by ${a.actor} · evidence: ${why}`));
  }
  $('aliases').hidden = aliases.length === 0;
}

function summary(sb) {
  $('summary').textContent = `${sb.policy} at version ${sb.version}: ${sb.rows.length} rows, baseline run ${sb.baseline}` +
    (sb.baseline_checkpoint ? ` of ${sb.baseline_checkpoint}` : ' of each row\'s checkpoint');
}

/** One reliability diagram per verifier the rows name (classifiers with calibration metrics). */
function renderVerifiers(sb) {
  const box = $('reliability');
  box.replaceChildren();
  const seen = new Set();
  for (const r of sb.rows) {
    const vq = r.verifier_quality;
    if (!vq || seen.has(vq.artifact_id) || !Array.isArray(vq.reliability)) continue;
    seen.add(vq.artifact_id);
    const S = 180;
    const pad = 24;
    const px = (v) => pad + v * (S - pad - 6);
    const py = (v) => S - pad - v * (S - pad - 6);
    const fig = el('figure', { class: 'reliability' });
    const s = svg('svg', { width: S, height: S, viewBox: `0 0 ${S} ${S}`, class: 'reliability', 'data-artifact': vq.artifact_id });
    s.appendChild(svg('rect', { x: px(0), y: py(1), width: px(1) - px(0), height: py(0) - py(1), fill: '#f8fafc', stroke: '#d1d5db' }));
    s.appendChild(svg('line', { x1: px(0), y1: py(0), x2: px(1), y2: py(1), stroke: '#9ca3af', 'stroke-dasharray': '3 3' }));
    for (const t of [0, 0.5, 1]) {
      const tx = svg('text', { x: px(t), y: S - 8, 'font-size': 10, 'text-anchor': 'middle', fill: '#6b7280' });
      tx.textContent = String(t);
      s.appendChild(tx);
      const ty = svg('text', { x: 4, y: py(t) + 3, 'font-size': 10, fill: '#6b7280' });
      ty.textContent = String(t);
      s.appendChild(ty);
    }
    const total = vq.reliability.reduce((a, bin) => a + bin.count, 0) || 1;
    for (const bin of vq.reliability) {
      if (!bin.count) continue;
      const c = svg('circle', { cx: px(bin.mean_predicted), cy: py(bin.fraction_positive), r: 2 + 6 * Math.sqrt(bin.count / total), fill: '#2563eb', 'fill-opacity': 0.7 });
      const t = svg('title', {});
      t.textContent = `${bin.count} samples: predicted ${bin.mean_predicted.toFixed(2)}, observed ${bin.fraction_positive.toFixed(2)}`;
      c.appendChild(t);
      s.appendChild(c);
    }
    fig.appendChild(s);
    const num = (x) => (typeof x === 'number' ? x.toFixed(3) : '-');
    fig.appendChild(el('figcaption', {}, `${vq.kind} ${vq.artifact_id.slice(0, 12)}: AUROC ${num(vq.auroc)} (action ${num(vq.action_auroc)}, obs-only ${num(vq.obs_only_auroc)}), accuracy ${num(vq.accuracy)}, Brier ${num(vq.brier)}, ECE ${num(vq.ece)} (${vq.val_samples} samples)`));
    if (vq.monitor) fig.appendChild(monitorLine(vq.monitor));
    box.appendChild(fig);
  }
  $('verifiers').hidden = seen.size === 0;
}

function params() {
  return {
    policy: $('f-policy').value,
    baseline: $('f-baseline').value,
    baseline_checkpoint: $('f-baseline-checkpoint').value,
    version: $('f-version').value,
  };
}

function syncHash(p) {
  history.replaceState(null, '', `#${q(p)}`);
}

async function load() {
  const p = params();
  syncHash(p);
  document.body.dataset.ready = '';
  $('error').textContent = '';
  $('dl-csv').href = `/v1/scoreboard?${q({ ...p, format: 'csv' })}`;
  $('dl-json').href = `/v1/scoreboard?${q(p)}`;
  $('dl-csv').setAttribute('download', `scoreboard-${p.policy}.csv`);
  $('dl-json').setAttribute('download', `scoreboard-${p.policy}.json`);
  try {
    const sb = await call('GET', `/v1/scoreboard?${q(p)}`);
    // The choices of baseline: the runs and checkpoints the rows name.
    const runs = [...new Set(sb.rows.map((r) => r.run_name))].sort();
    const ckpts = [...new Set(sb.rows.map((r) => r.checkpoint))].sort();
    fill($('f-baseline'), runs, sb.baseline);
    fill($('f-baseline-checkpoint'), ckpts, sb.baseline_checkpoint || '', "each row's own");
    const badges = render(sb);
    summary(sb);
    await Promise.all([...badges.map((x) => fillBadge(x, sb)), renderAliases(sb.policy)]);
    window.ufopsScoreboard = sb;
    document.body.dataset.ready = String(sb.version);
  } catch (e) {
    $('error').textContent = e instanceof ApiError ? e.message : String(e);
    document.body.dataset.ready = 'error';
  }
}

function fill(select, values, current, emptyLabel) {
  select.replaceChildren();
  if (emptyLabel !== undefined) select.appendChild(el('option', { value: '' }, emptyLabel));
  const all = values.includes(current) || current === '' ? values : [current, ...values];
  for (const v of all) select.appendChild(el('option', { value: v }, v));
  select.value = current;
}

async function main() {
  let me;
  try {
    me = await call('GET', '/ui/session');
  } catch (e) {
    $('need-signin').hidden = false;
    return;
  }
  $('me').textContent = `${me.name} (${me.role})`;
  $('board').hidden = false;
  const hash = new URLSearchParams(location.hash.slice(1));
  const policies = await call('GET', '/v1/policies');
  const names = policies.map((p) => (typeof p === 'string' ? p : p.name));
  const want = hash.get('policy') || names[0] || '';
  fill($('f-policy'), names, want);
  fill($('f-baseline'), [], hash.get('baseline') || 'base');
  fill($('f-baseline-checkpoint'), [], hash.get('baseline_checkpoint') || '', "each row's own");
  $('f-version').value = hash.get('version') || '';
  for (const id of ['f-policy', 'f-baseline', 'f-baseline-checkpoint', 'f-version']) $(id).addEventListener('change', load);
  $('controls').addEventListener('submit', (e) => { e.preventDefault(); load(); });
  await load();
}

main();
