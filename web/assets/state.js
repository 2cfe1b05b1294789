// The labeling page's state: one object that the page's modules (app.js, signin.js, queue.js,
// episode.js, labeling.js, keys.js) import and change, and the measurements the end-to-end test
// reads. Both are on `window.ufops` for the tests.

export const LABELS = ['success', 'failure', 'unknown'];

export const S = {
  me: null,
  player: null,      // the Player under the cameras (player.js), made once at start
  filters: { policy: '', checkpoint: '', task: '', label: '', order: '' },
  hashEpisode: '',   // the episode of the link (`#ep=`), read with the filters
  pageSize: 100,    // episodes per page of the queue (`#pagesize=N`)
  queue: [],        // the loaded part of the queue, in order (unknown first by default)
  seen: new Set(),  // ids in `queue`
  pager: null,      // where the next page of the queue comes from
  queueSeq: 0,
  counts: { total: 0, success: 0, failure: 0, unknown: 0 }, // server counts, adjusted locally
  countsTimer: null, // a server count asked for once the writes settle
  pendingWrites: 0, // label writes in flight (server counts are taken only without any)
  writeGen: 0,
  idx: -1,
  cur: null,        // the prepared episode on screen
  cache: new Map(), // id -> prepared episode (prefetch)
  selected: new Set(),
  plots: null,
  score: null,      // the verifier score plot (review_queue.js)
  steering: null,   // the best-of-N score spread of a steered episode (steering.js)
  takeovers: null,  // the human-takeover strip under the scrub bar (takeovers.js)
  traj: null,
  showSeq: 0,
  conflicts: [],    // pending conflicts to ask about
  conflictOpen: false,
};

// The episode view's entry (`show(i)` of episode.js), set by app.js at start: the queue opens
// episodes through it, so queue.js need not import episode.js, which imports queue.js.
export const views = { show: null };

// Measurements the end-to-end test reads (and the page shows): keyboard actions, and the time
// from a verdict key to the next episode being playable.
export const metrics = { keyActions: 0, verdicts: 0, advances: [] };
window.ufops = { metrics, state: S };
