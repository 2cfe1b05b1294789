// The labeling page: sign-in, the queue (filters, counts, campaign progress, bulk labels), the
// episode view (synced cameras, plots, metadata, history), keyboard labeling with auto-advance
// and prefetching, and conflict resolution. Plain ES modules, no build step.
//
// The queue is fetched a page at a time as the labeler moves through it (keyset pages of
// /v1/episodes), and the counts and progress bar come from /v1/episodes/counts: the page never
// reads every episode of a campaign, whatever its size.
//
// This module starts the page; the rest is in state.js (the one state object every module
// imports), signin.js, queue.js, episode.js, labeling.js and keys.js (the keyboard and every
// control's handler). dom.js holds the DOM helpers all the page's scripts share.

import * as api from './api.js';
import { Player } from './player.js';
import { $ } from './dom.js';
import { S, views } from './state.js';
import { show } from './episode.js';
import { wire } from './keys.js';
import { enter, showSignIn } from './signin.js';

async function start() {
  views.show = show;
  S.player = new Player({
    grid: $('videos'), scrub: $('scrub'), frameOut: $('frame'), playButton: $('play'),
    onFrame: (f) => { if (S.plots) S.plots.setFrame(f); if (S.score) S.score.setFrame(f); if (S.steering) S.steering.setFrame(f); if (S.takeovers) S.takeovers.setFrame(f); if (S.traj) S.traj.setFrame(f); },
  });
  wire();
  try {
    S.me = await api.session();
    await enter();
  } catch (e) {
    showSignIn(e.status === 401 ? '' : e.message);
  }
}

start();
