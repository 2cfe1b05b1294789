// The page's calls to the ufops API. Authentication is the HttpOnly session cookie set by
// POST /ui/session; every request carries X-Ufops-UI: 1 (the server's CSRF rule for
// cookie-authenticated writes). Errors are problem documents, thrown as ApiError.

export class ApiError extends Error {
  constructor(status, problem) {
    super((problem && (problem.detail || problem.title)) || `HTTP ${status}`);
    this.status = status;
    this.problem = problem || {};
  }
}

export async function call(method, path, { body, headers } = {}) {
  const h = { 'X-Ufops-UI': '1', Accept: 'application/json', ...(headers || {}) };
  if (body !== undefined) h['Content-Type'] = 'application/json';
  let resp;
  try {
    resp = await fetch(path, {
      method, headers: h, credentials: 'same-origin', cache: 'no-store',
      body: body === undefined ? undefined : JSON.stringify(body),
    });
  } catch (e) {
    throw new ApiError(0, { title: 'network error', detail: `the server did not answer (${e.message})` });
  }
  if (resp.status === 204) return null;
  const text = await resp.text();
  let json = null;
  try { json = text ? JSON.parse(text) : null; } catch { json = { detail: text }; }
  if (!resp.ok) throw new ApiError(resp.status, json);
  return json;
}

const q = (params) => {
  const u = new URLSearchParams();
  for (const [k, v] of Object.entries(params)) if (v !== undefined && v !== null && v !== '') u.set(k, v);
  const s = u.toString();
  return s ? `?${s}` : '';
};

export const session = () => call('GET', '/ui/session');
export const signIn = (token) => call('POST', '/ui/session', { body: { token } });
export const signOut = () => call('DELETE', '/ui/session');
export const policies = () => call('GET', '/v1/policies');
export const checkpoints = (policy) => call('GET', `/v1/checkpoints${q({ policy })}`);
export const tasks = () => call('GET', '/v1/tasks');
export const episode = (id) => call('GET', `/v1/episodes/${encodeURIComponent(id)}`);
export const steps = (id) => call('GET', `/v1/episodes/${encodeURIComponent(id)}/steps`);
export const mediaUrl = (id, key) => `/v1/episodes/${encodeURIComponent(id)}/media/${encodeURIComponent(key)}`;
/** Step t of an image camera (a PNG; cached by the browser for good). */
export const frameUrl = (id, camera, t) =>
  `/v1/episodes/${encodeURIComponent(id)}/frames/${encodeURIComponent(camera)}/${t}`;

/** One page of episodes matching the filters, in id order; `after` is the previous page's
 *  `next_cursor` (keyset pages: fast at any depth, no repeats while labels change). */
export const episodesPage = (filters, after, limit) =>
  call('GET', `/v1/episodes${q({ ...filters, limit, after })}`);

/** Episodes per label state and their total, counted by the server (kept with every write). */
export const counts = (filters) => call('GET', `/v1/episodes/counts${q(filters)}`);

/** PUT a label against the revision the labeler saw; 409 → ApiError with the current label. */
export const putLabel = (id, label, revision, note) =>
  call('PUT', `/v1/episodes/${encodeURIComponent(id)}/label`, {
    body: { label, note: note || null }, headers: { 'If-Match': `"${revision}"` },
  });

export const bulkLabel = (updates) => call('POST', '/v1/labels/bulk', { body: { updates } });
