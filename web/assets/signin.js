// Sign-in and sign-out screens: the token form shown until a session exists, and entering the
// page (who is signed in, the filters and the queue from the link).

import * as consensus from './consensus.js';
import { $ } from './dom.js';
import { S } from './state.js';
import { loadFilters, loadQueue, readHash } from './queue.js';

export function showSignIn(msg) {
  $('app').hidden = true;
  $('signin').hidden = false;
  $('signin-error').textContent = msg || '';
  $('token').value = '';
  $('token').focus();
}

export async function enter() {
  $('signin').hidden = true;
  $('app').hidden = false;
  $('me').textContent = `${S.me.name} (${S.me.role})`;
  consensus.init(S.me);
  if (document.activeElement && document.activeElement !== document.body) document.activeElement.blur();
  readHash();
  await loadFilters();
  await loadQueue(S.hashEpisode);
}
