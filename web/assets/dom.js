// DOM helpers shared by the page's scripts: element by id, HTML escaping for template strings,
// a status line's text and kind, and a new element with attributes and text.

/** The element with this id. */
export const $ = (id) => document.getElementById(id);

/** `s` as text safe inside HTML (and attribute values): `null`/`undefined` become ''. */
export function esc(s) {
  return String(s ?? '').replace(/[&<>"']/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;' }[c]));
}

/** Sets a status line (`.status`): its text and kind (`ok`, `error` or none). */
export function status(el, text, kind) {
  el.textContent = text || '';
  el.className = `status ${kind || ''}`;
}

/** A new `tag` element with attributes `attrs` and, if given, text content `text`. */
export function el(tag, attrs = {}, text) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}
