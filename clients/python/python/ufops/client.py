"""``ufops.Client``: the ``ufops serve`` HTTP API from Python (standard library only).

Reads episodes (keyset pages, followed to the end) and writes labels with optimistic
concurrency: :meth:`Client.set_label` sends ``If-Match: <revision>``, and a label changed by
someone else since it was read raises :class:`~ufops.errors.ConflictError` saying who changed it.
"""
from __future__ import annotations

import json
import urllib.error
import urllib.parse
import urllib.request
from typing import Any, Dict, List, Optional

from ufops.errors import AuthError, ConflictError, FetchError, NotFoundError, UfopsError

JsonObject = Dict[str, Any]


class Client:
    """A client of ``ufops serve`` at ``url`` (``http://host:port``) with a bearer ``token``."""

    def __init__(self, url: str, token: str, *, timeout: float = 60.0) -> None:
        self.url = url.rstrip("/")
        self.token = token
        self.timeout = timeout

    def __repr__(self) -> str:
        return f"Client({self.url!r})"

    def _request(
        self, method: str, path: str, body: Optional[JsonObject] = None, headers: Optional[Dict[str, str]] = None
    ) -> tuple[Any, Dict[str, str]]:
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.url + path, data=data, method=method)
        req.add_header("Authorization", f"Bearer {self.token}")
        if data is not None:
            req.add_header("Content-Type", "application/json")
        for k, v in (headers or {}).items():
            req.add_header(k, v)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                raw = resp.read()
                return (json.loads(raw) if raw else None), dict(resp.headers.items())
        except urllib.error.HTTPError as e:
            raise _error(method, path, e.code, e.read()) from None
        except urllib.error.URLError as e:
            raise FetchError(f"{method} {self.url}{path}: {e.reason}") from None

    def episodes(self, **filters: Any) -> List[JsonObject]:
        """All episodes matching ``filters`` (policy, checkpoint, task, label, label_source, tag,
        version) as records, following the API's pages to the end."""
        out: List[JsonObject] = []
        query = {k: str(v) for k, v in filters.items() if v is not None}
        query.setdefault("limit", "1000")
        while True:
            page, _ = self._request("GET", "/v1/episodes?" + urllib.parse.urlencode(query))
            out.extend(page["episodes"])
            cursor = page.get("next_cursor")
            if not cursor:
                return out
            query["after"] = cursor

    def episodes_frame(self, **filters: Any) -> Any:
        """:meth:`episodes` as a polars DataFrame (the columns of ``Store.episodes``)."""
        from ufops.store import episodes_frame

        return episodes_frame(self.episodes(**filters))

    def episode(self, episode_id: str) -> JsonObject:
        """One episode's record (its ``label_revision`` is what :meth:`set_label` expects)."""
        body, _ = self._request("GET", f"/v1/episodes/{urllib.parse.quote(episode_id, safe='')}")
        return body["episode"]  # type: ignore[no-any-return]

    def label_history(self, episode_id: str) -> List[JsonObject]:
        """The episode's label events, oldest first (who set what, when)."""
        body, _ = self._request("GET", f"/v1/episodes/{urllib.parse.quote(episode_id, safe='')}")
        return body["history"]  # type: ignore[no-any-return]

    def set_label(self, episode_id: str, label: str, revision: int, note: Optional[str] = None) -> JsonObject:
        """Sets the label (``success``, ``failure`` or ``unknown``) if the episode is still at
        label ``revision``; returns the change (its ``revision`` is the new one). Raises
        :class:`ConflictError` when someone changed the label since."""
        body: JsonObject = {"label": label}
        if note is not None:
            body["note"] = note
        change, _ = self._request(
            "PUT",
            f"/v1/episodes/{urllib.parse.quote(episode_id, safe='')}/label",
            body,
            {"If-Match": f'"{revision}"'},
        )
        return change  # type: ignore[no-any-return]


def _error(method: str, path: str, status: int, raw: bytes) -> UfopsError:
    try:
        problem = json.loads(raw)
    except ValueError:
        problem = {}
    if not isinstance(problem, dict):
        problem = {}
    detail = problem.get("detail") or raw[:300].decode(errors="replace")
    msg = f"{method} {path}: status {status}: {detail}"
    if status == 409 and problem.get("set_by") is not None:
        return ConflictError(
            f"{msg} (changed by {problem.get('set_by')} at {problem.get('set_at')})",
            actor=problem.get("set_by"),
            revision=problem.get("current_revision"),
            label=problem.get("current_label"),
            at=problem.get("set_at"),
        )
    if status == 409:
        return ConflictError(msg)
    if status in (401, 403):
        return AuthError(msg)
    if status == 404:
        return NotFoundError(msg)
    if 400 <= status < 500:
        return ValueError(msg)  # type: ignore[return-value]
    return FetchError(msg)
