-- The change feed and idempotent requests. Kept in step with the other backend's history.
--
-- Every catalog change writes its events in the transaction that makes the change (store/src/
-- events.rs). Sequence numbers come from `event_head`, whose one row each such transaction
-- updates as its last statement: the row stays locked until the commit, so numbers are handed
-- out in commit order and a reader that saw `seq` N never later finds a new event below N.
-- `pruned_through` is the highest sequence number retention deleted (0: none). `created_ms`
-- grows with `seq` (both are taken under the same lock), so retention finds its cut by
-- bisecting the primary key: no second index for every event to pay for.
CREATE TABLE event_head (
    id BIGINT PRIMARY KEY,
    seq BIGINT NOT NULL,
    pruned_through BIGINT NOT NULL
);
INSERT INTO event_head (id, seq, pruned_through) VALUES (1, 0, 0);
CREATE TABLE events (
    seq BIGINT PRIMARY KEY,
    kind TEXT NOT NULL,
    subject TEXT NOT NULL,
    policy TEXT,
    checkpoint TEXT,
    data TEXT NOT NULL,
    created_at TEXT NOT NULL,
    created_ms BIGINT NOT NULL
);
-- A request sent with an `Idempotency-Key` header, per principal (the token's id): its body's
-- hash, and once answered the response, replayed to a retry until `expires_ms`. A claim being
-- served has no status yet and a lease its server renews; `committed_seq` is set by the
-- transaction that made the request's change, so a retry after a crash knows the work is done.
CREATE TABLE idempotency_keys (
    principal TEXT NOT NULL,
    key TEXT NOT NULL,
    method TEXT NOT NULL,
    path TEXT NOT NULL,
    request_sha256 TEXT NOT NULL,
    lease_until_ms BIGINT NOT NULL,
    committed_seq BIGINT,
    status BIGINT,
    headers TEXT,
    body BLOB,
    created_ms BIGINT NOT NULL,
    expires_ms BIGINT NOT NULL,
    PRIMARY KEY (principal, key)
);
CREATE INDEX idempotency_keys_by_expiry ON idempotency_keys (expires_ms);
