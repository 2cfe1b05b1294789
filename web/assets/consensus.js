// Several labelers on the labeling page. For the episode on screen: its policy's
// campaign (how many labelers must agree, blind or not), the task's failure causes on the number
// keys 1-9 (0 clears the cause and the spans), time spans marked with [ (start) and ] (end) at
// the frame shown, and the episode's votes — in a blind campaign only how many there are until
// you have given yours. Beside the queue: the campaign's agreement (per-labeler counts, Cohen's κ
// per pair, Krippendorff's α) and, for admins, the adjudication queue with one button per verdict.
//
// A verdict goes out as a vote (POST /v1/episodes/{id}/votes) when the campaign needs several
// labelers or the verdict carries a cause or spans; otherwise as the plain PUT it always was.

import { call, putLabel } from './api.js';
import { $, esc } from './dom.js';

const enc = encodeURIComponent;

const campaigns = new Map(); // policy → Promise<campaign>
const taxonomies = new Map(); // task → Promise<causes>
const mine = new Set(); // episodes this labeler voted on in this session
let me = { name: '', role: 'viewer' };
let draft = fresh(null);
let reviewPolicy = null;
let reviewTimer = null;

function fresh(ep) {
  return { id: ep ? ep.id : null, ep, campaign: null, causes: [], cause: null, spans: [], start: null };
}

function cached(map, key, load) {
  if (!map.has(key)) map.set(key, load().catch((e) => { map.delete(key); throw e; }));
  return map.get(key);
}

export const campaignOf = (policy) => cached(campaigns, policy, () => call('GET', `/v1/campaigns/${enc(policy)}`));
export const causesOf = (task) =>
  cached(taxonomies, task || '*', () => call('GET', `/v1/tasks/${enc(task || '*')}/failure-causes`).then((r) => r.causes));

export function init(session) {
  me = session;
  $('review').hidden = false;
  $('adjudication-box').hidden = me.role !== 'admin';
}

/** Whether this labeler gave a verdict on the episode in this session: in a voting campaign
 *  its label stays as it was until enough labelers agree, but it is done for them. */
export const voted = (id) => mine.has(id);

/** The episode on screen changed (or was reloaded). */
export async function show(ep) {
  if (draft.id !== ep.id) draft = fresh(ep);
  draft.ep = ep;
  try {
    const [c, causes] = await Promise.all([campaignOf(ep.policy), causesOf(ep.task)]);
    if (draft.id !== ep.id) return;
    draft.campaign = c;
    draft.causes = causes;
  } catch { /* the panel shows what it has */ }
  render();
  loadVotes(ep.id);
  if (reviewPolicy !== ep.policy) refreshReview(ep.policy);
}

function render() {
  const c = draft.campaign;
  $('campaign').textContent = c
    ? (c.labels_needed > 1 ? `campaign: ${c.labels_needed} labelers must agree${c.blind ? ', blind' : ''}` : 'campaign: one labeler per episode')
    : '';
  $('causes').innerHTML = draft.causes.length
    ? draft.causes.map((name, i) =>
      `<li class="${draft.cause === name ? 'chosen' : ''}" data-cause="${esc(name)}"><kbd>${i + 1}</kbd> ${esc(name)}</li>`).join('')
    : '<li class="sub">no failure causes set for this task</li>';
  const spans = draft.spans.map((s) => `<li data-span="${s.start_step}-${s.end_step}">steps ${s.start_step}–${s.end_step}</li>`);
  if (draft.start !== null) spans.push(`<li class="open">from step ${draft.start} … (<kbd>]</kbd> ends it)</li>`);
  $('spans').innerHTML = spans.join('') || '<li class="sub">no span (<kbd>[</kbd> start, <kbd>]</kbd> end)</li>';
}

async function loadVotes(id) {
  let v;
  try {
    v = await call('GET', `/v1/episodes/${enc(id)}/votes`);
  } catch { return; }
  if (draft.id !== id) return;
  const box = $('votes');
  box.dataset.state = v.state;
  box.dataset.voters = String(v.voters);
  box.dataset.hidden = String(v.hidden);
  const head = `<div class="sub">${esc(v.state)} · ${v.voters}/${v.labels_needed} labeler${v.labels_needed > 1 ? 's' : ''}</div>`;
  box.innerHTML = head + (v.hidden
    ? `<p class="sub" id="votes-hidden">${v.voters} verdict${v.voters === 1 ? '' : 's'} hidden until you give yours</p>`
    : `<ul>${v.votes.map((x) => `<li data-actor="${esc(x.actor)}"><span class="badge ${esc(x.label)}">${esc(x.label)}</span>
        <b>${esc(x.actor)}</b>${x.failure_cause ? ` · ${esc(x.failure_cause)}` : ''}${(x.spans || []).length ? ` · ${x.spans.map((s) => `${s.start_step}–${s.end_step}`).join(', ')}` : ''}</li>`).join('')}</ul>`);
}

/** Number keys choose a failure cause, [ and ] mark a span at `frame`; true if the key was ours. */
export function onKey(k, frame) {
  if (!draft.id) return false;
  if (k >= '1' && k <= '9' && k.length === 1) {
    const name = draft.causes[Number(k) - 1];
    if (name === undefined) return false;
    draft.cause = draft.cause === name ? null : name;
  } else if (k === '0') {
    Object.assign(draft, { cause: null, spans: [], start: null });
  } else if (k === '[') {
    draft.start = frame;
  } else if (k === ']') {
    if (draft.start === null) return false;
    draft.spans.push({ start_step: Math.min(draft.start, frame), end_step: Math.max(draft.start, frame) });
    draft.start = null;
  } else return false;
  render();
  return true;
}

/** Saves a verdict on `ep` seen at `revision`: a vote or a plain PUT (see the top). Resolves to
 *  `{label, revision, actor}` of the episode afterwards; a stale revision throws the PUT's 409. */
export async function save(ep, label, revision, note) {
  // Taken before any await: the page moves on to the next episode (a new draft) at once.
  const d = draft.id === ep.id ? draft : fresh(ep);
  if (draft.id === ep.id) draft = fresh(ep);
  let c = null;
  try { c = await campaignOf(ep.policy); } catch { /* a PUT then; the server refuses it if votes are needed */ }
  const cause = label === 'failure' ? d.cause : null;
  if ((!c || c.labels_needed <= 1) && !cause && !d.spans.length) {
    return putLabel(ep.id, label, revision, note);
  }
  const out = await call('POST', `/v1/episodes/${enc(ep.id)}/votes`, {
    body: { label, note: note || null, failure_cause: cause, spans: d.spans, expect_revision: revision },
  });
  mine.add(ep.id);
  scheduleReview(ep.policy);
  return { label: out.label, revision: out.revision, actor: out.change ? out.change.actor : ep.label_actor };
}

function scheduleReview(policy) {
  clearTimeout(reviewTimer);
  reviewTimer = setTimeout(() => refreshReview(policy), 300);
}

const num = (x, d = 3) => (x === null || x === undefined ? '—' : Number(x).toFixed(d));

/** The campaign's agreement and (admins) its disputes. */
export async function refreshReview(policy) {
  reviewPolicy = policy;
  if (!policy) return;
  try {
    const ag = await call('GET', `/v1/agreement?policy=${enc(policy)}`);
    const box = $('agreement');
    box.dataset.alpha = ag.krippendorff_alpha ?? '';
    box.innerHTML = `<p class="sub">${ag.agreed} agreed · ${ag.disputed} disputed · ${ag.settled} settled · ${ag.pending} pending</p>
      <table><tr><th>labeler</th><th>votes</th><th>s</th><th>f</th><th>u</th></tr>${ag.labelers.map((l) =>
        `<tr><td>${esc(l.actor)}</td><td>${l.votes}</td><td>${l.success}</td><td>${l.failure}</td><td>${l.unknown}</td></tr>`).join('')}</table>
      <table><tr><th>pair</th><th>n</th><th>agree</th><th>κ</th></tr>${ag.pairs.map((p) =>
        `<tr class="pair" data-a="${esc(p.a)}" data-b="${esc(p.b)}" data-kappa="${p.kappa ?? ''}"><td>${esc(p.a)} · ${esc(p.b)}</td>
         <td>${p.episodes}</td><td>${num(p.observed, 2)}</td><td>${num(p.kappa)}</td></tr>`).join('')}</table>
      <p>Krippendorff's α: <b id="alpha">${num(ag.krippendorff_alpha)}</b></p>`;
  } catch { /* shown next time */ }
  if (me.role !== 'admin') return;
  try {
    const q = await call('GET', `/v1/adjudication?policy=${enc(policy)}`);
    $('adjudication').innerHTML = q.length
      ? q.map((d) => `<li data-episode="${esc(d.episode_id)}"><code>${esc(d.episode_id)}</code>
          ${d.votes.map((v) => `<span class="badge ${esc(v.label)}">${esc(v.actor)}: ${esc(v.label)}</span>`).join(' ')}
          <span class="settle">${['success', 'failure', 'unknown'].map((l) =>
            `<button type="button" data-settle="${l}" data-episode="${esc(d.episode_id)}">${l}</button>`).join('')}</span></li>`).join('')
      : '<li class="sub">no disputes</li>';
  } catch { /* shown next time */ }
}

async function settle(id, label) {
  try {
    await call('POST', `/v1/episodes/${enc(id)}/adjudication`, { body: { label } });
  } catch (e) {
    $('adjudication-status').textContent = `not settled: ${e.message}`;
    return;
  }
  $('adjudication-status').textContent = `${id} settled: ${label}`;
  await refreshReview(reviewPolicy);
  if (draft.id === id) loadVotes(id);
}

export function wire() {
  $('adjudication').addEventListener('click', (ev) => {
    const b = ev.target.closest('button[data-settle]');
    if (b) settle(b.dataset.episode, b.dataset.settle);
  });
  $('review-refresh').addEventListener('click', () => refreshReview(reviewPolicy));
}
