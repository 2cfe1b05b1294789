"""``ufops.Client``: the ``ufops serve`` HTTP API from Python (standard library only).

Reads episodes (keyset pages, followed to the end) and writes labels with optimistic
concurrency: :meth:`Client.set_label` sends ``If-Match: <revision>``, and a label changed by
someone else since it was read raises :class:`~ufops.errors.ConflictError` saying who changed it.
"""
from __future__ import annotations

import json
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from typing import Any, Dict, Iterator, List, Optional, Sequence

from ufops.errors import AuthError, ConflictError, FetchError, NotFoundError, UfopsError

JsonObject = Dict[str, Any]

# Tries of a layer write that failed in transit or with a 5xx (one idempotency key for all).
WRITE_TRIES = 3


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

    def _request_bytes(
        self, method: str, path: str, data: Optional[bytes] = None, headers: Optional[Dict[str, str]] = None
    ) -> bytes:
        return self._request_raw(method, path, data, headers)[0]

    def _request_raw(
        self, method: str, path: str, data: Optional[bytes] = None, headers: Optional[Dict[str, str]] = None
    ) -> tuple[bytes, Dict[str, str]]:
        req = urllib.request.Request(self.url + path, data=data, method=method)
        req.add_header("Authorization", f"Bearer {self.token}")
        for k, v in (headers or {}).items():
            req.add_header(k, v)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                return resp.read(), {k.lower(): v for k, v in resp.headers.items()}
        except urllib.error.HTTPError as e:
            raise _error(method, path, e.code, e.read()) from None
        except urllib.error.URLError as e:
            raise FetchError(f"{method} {self.url}{path}: {e.reason}") from None

    def layer_store(self) -> "ApiLayerStore":
        """This server as the store :func:`ufops.features.compute_layer` takes: frames read by
        range requests on the episodes' media, the layer written through ``POST /v1/layers``
        (role trainer)."""
        return ApiLayerStore(self)

    def steps(self, episode_id: str, version: Optional[int] = None, *, layers: Optional[List[str]] = None) -> Any:
        """One episode's steps as a polars DataFrame (read as Arrow IPC), with ``layers`` joined as
        ``obs.<layer>`` columns."""
        import io

        import polars as pl

        query: Dict[str, str] = {}
        if version is not None:
            query["version"] = str(version)
        if layers:
            query["layers"] = ",".join(layers)
        path = f"/v1/episodes/{urllib.parse.quote(episode_id, safe='')}/steps"
        if query:
            path += "?" + urllib.parse.urlencode(query)
        raw = self._request_bytes("GET", path, headers={"Accept": "application/vnd.apache.arrow.stream"})
        return pl.read_ipc_stream(io.BytesIO(raw))

    def layers(self) -> List[JsonObject]:
        """Every (layer, producer) pair with the episodes holding it now."""
        body, _ = self._request("GET", "/v1/layers")
        return body  # type: ignore[no-any-return]

    def layer_episodes(self, name: str, producer_hash: str) -> List[str]:
        """The episodes holding layer ``name`` from the producer ``producer_hash`` now."""
        q = urllib.parse.urlencode({"producer_hash": producer_hash})
        body, _ = self._request("GET", f"/v1/layers/{urllib.parse.quote(name, safe='')}/episodes?{q}")
        return body  # type: ignore[no-any-return]

    def write_layer(self, name: str, producer: Dict[str, Any], values: Dict[str, Any]) -> JsonObject:
        """:meth:`ufops.Store.write_layer` over the API (role trainer): one group of episodes'
        values (episode id → float32 ``(steps, dim)``) as one new version, sent as Arrow IPC."""
        import io

        import numpy as np
        import polars as pl

        ids: List[str] = []
        rows: List[Any] = []
        dim = None
        for episode_id, v in values.items():
            a = np.ascontiguousarray(np.asarray(v, dtype=np.float32))
            if a.ndim != 2 or (dim is not None and a.shape[1] != dim):
                raise ValueError(f"layer {name}: episode {episode_id} values have shape {a.shape}, expected (steps, dim)")
            dim = a.shape[1]
            ids.extend([episode_id] * a.shape[0])
            rows.append(a)
        if dim is None:
            raise ValueError(f"layer {name}: no episodes given")
        frame = pl.DataFrame(
            {
                "episode_id": pl.Series(ids, dtype=pl.Utf8),
                "value": pl.Series(np.concatenate(rows), dtype=pl.Array(pl.Float32, dim)),
            }
        )
        buf = io.BytesIO()
        frame.write_ipc_stream(buf, compat_level=pl.CompatLevel.oldest())
        q = urllib.parse.urlencode({"producer": json.dumps(producer, sort_keys=True)})
        # One key for this group's tries: a retry after a lost response gets the first answer
        # (its version) replayed instead of writing again.
        headers = {"Content-Type": "application/vnd.apache.arrow.stream", "Idempotency-Key": f"layer-{uuid.uuid4()}"}
        for attempt in range(WRITE_TRIES):
            try:
                raw = self._request_bytes(
                    "POST", f"/v1/layers/{urllib.parse.quote(name, safe='')}?{q}", buf.getvalue(), headers
                )
                return json.loads(raw)  # type: ignore[no-any-return]
            except FetchError:
                if attempt + 1 == WRITE_TRIES:
                    raise
                time.sleep(0.5 * 2**attempt)
        raise AssertionError("unreachable")

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


    def events(
        self,
        after: int = 0,
        *,
        kinds: Optional[Sequence[str]] = None,
        policy: Optional[str] = None,
        wait: float = 0,
        limit: int = 1000,
    ) -> JsonObject:
        """One page of the change feed (``GET /v1/events``): ``{"events": [...], "next": N,
        "head": H}``, events with a sequence number above ``after``, oldest first. ``kinds``
        (``"label.set"``, ``"job.changed"``, ...) and ``policy`` filter; with ``wait`` seconds (at
        most 60) an empty page waits for the next matching event."""
        query: Dict[str, str] = {"after": str(after), "limit": str(limit), "wait": str(int(wait))}
        if kinds:
            query["kind"] = ",".join(kinds)
        if policy is not None:
            query["policy"] = policy
        page, _ = self._request("GET", "/v1/events?" + urllib.parse.urlencode(query))
        return page  # type: ignore[no-any-return]

    def follow_events(
        self, after: int = 0, *, kinds: Optional[Sequence[str]] = None, policy: Optional[str] = None
    ) -> Iterator[JsonObject]:
        """Every event after ``after`` as it commits, forever (long polling): ``for e in
        client.follow_events(kinds=["job.changed"]): ...``. Remember the last ``e["seq"]`` to
        resume from it."""
        while True:
            page = self.events(after, kinds=kinds, policy=policy, wait=min(30.0, self.timeout / 2))
            yield from page["events"]
            after = page["next"]

    def automations(self, policy: Optional[str] = None) -> List[JsonObject]:
        """Every automation (of ``policy``), oldest first, with its cursor in the feed and how
        many jobs it queued."""
        query = "" if policy is None else "?" + urllib.parse.urlencode({"policy": policy})
        body, _ = self._request("GET", "/v1/automations" + query)
        return body  # type: ignore[no-any-return]

    def create_automation(self, policy: str, rule: str, params: Optional[JsonObject] = None) -> JsonObject:
        """Declares an automation (a trainer token): ``rule`` is ``"train_on_labels"`` (``params``
        needs ``min_labeled``), ``"score_on_publish"`` or ``"scoreboard_on_run_labeled"``. From then
        on the server queues its jobs from the change feed, each an ``automation.fired`` event."""
        body, _ = self._request("POST", "/v1/automations", {"policy": policy, "rule": rule, "params": params or {}})
        return body  # type: ignore[no-any-return]

    def delete_automation(self, automation_id: str) -> None:
        """Deletes an automation (the jobs it queued go on)."""
        self._request("DELETE", f"/v1/automations/{urllib.parse.quote(automation_id, safe='')}")


class ApiLayerStore:
    """:class:`Client` as a :class:`ufops.features.LayerStore`: what ``compute_layer`` reads and
    writes, over the API. A video is read by range requests on ``/v1/episodes/{id}/media/{key}``
    of an episode whose steps named it (the route serves the whole video object the episode's
    frames are in), so ``steps`` must have been read before a video is opened."""

    def __init__(self, client: Client) -> None:
        self.client = client
        self._media: Dict[str, tuple[str, str]] = {}

    def episodes(self) -> Any:
        return self.client.episodes_frame()

    def steps(self, ids: Any, /) -> Any:
        import polars as pl

        frames = []
        for episode_id in [ids] if isinstance(ids, str) else list(ids):
            f = self.client.steps(episode_id)
            for col in f.columns:
                if col.startswith("media.") and col.endswith(".path") and f.height:
                    for path in f[col].unique().to_list():
                        self._media.setdefault(path, (episode_id, col[len("media.") : -len(".path")]))
            frames.append(f)
        if not frames:
            return pl.DataFrame()
        return frames[0] if len(frames) == 1 else pl.concat(frames, how="diagonal_relaxed")

    def _media_path(self, path: str) -> str:
        if path not in self._media:
            raise NotFoundError(f"video {path}: no episode read so far shows it (read its steps first)")
        episode_id, key = self._media[path]
        q = urllib.parse.quote
        return f"/v1/episodes/{q(episode_id, safe='')}/media/{q(key, safe='')}"

    def object_size(self, path: str, /) -> int:
        _, headers = self.client._request_raw("GET", self._media_path(path), headers={"Range": "bytes=0-0"})
        total = headers.get("content-range", "").rsplit("/", 1)[-1]
        if not total.isdigit():
            raise FetchError(f"video {path}: the server sent no size (Content-Range {headers.get('content-range')!r})")
        return int(total)

    def read_object_range(self, path: str, start: int, end: int, /) -> bytes:
        if end <= start:
            return b""
        body, _ = self.client._request_raw("GET", self._media_path(path), headers={"Range": f"bytes={start}-{end - 1}"})
        return body

    def producer_hash(self, producer: Dict[str, Any], /) -> str:
        from ufops import _ufops

        return _ufops.Store.producer_hash(json.dumps(dict(producer)))

    def layer_episodes(self, name: str, producer_hash: str, /) -> List[str]:
        return self.client.layer_episodes(name, producer_hash)

    def write_layer(self, name: str, producer: Dict[str, Any], values: Dict[str, Any], /) -> JsonObject:
        return self.client.write_layer(name, producer, values)


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
