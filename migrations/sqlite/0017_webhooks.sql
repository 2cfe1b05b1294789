-- Webhooks: subscriptions to the change feed, delivered by the servers (api/src/webhooks.rs).
-- Kept in step with the other backend's history.
--
-- A subscription is a cursor into `events`: `cursor_seq` is the last event it delivered (or
-- gave up on); the next matching event is delivered until its receiver answers 2xx, retried with
-- back-off (`attempts`, `next_attempt_ms`), and after `max_attempts` failures recorded in
-- `webhook_dead_letters` and passed. Everything is rows, so a restart loses nothing; a server
-- delivers a subscription only while it holds its lease, so two servers never deliver it at once.
CREATE TABLE webhooks (
    id TEXT PRIMARY KEY,
    url TEXT NOT NULL,
    secret TEXT NOT NULL,
    kinds TEXT NOT NULL,
    policy TEXT,
    max_attempts BIGINT NOT NULL,
    cursor_seq BIGINT NOT NULL,
    attempts BIGINT NOT NULL,
    next_attempt_ms BIGINT NOT NULL,
    last_error TEXT,
    delivered BIGINT NOT NULL,
    lease_owner TEXT,
    lease_until_ms BIGINT NOT NULL,
    created_by TEXT NOT NULL,
    created_at TEXT NOT NULL
);
CREATE TABLE webhook_dead_letters (
    webhook_id TEXT NOT NULL REFERENCES webhooks(id) ON DELETE CASCADE,
    seq BIGINT NOT NULL,
    delivery_id TEXT NOT NULL,
    attempts BIGINT NOT NULL,
    last_error TEXT NOT NULL,
    created_at TEXT NOT NULL,
    PRIMARY KEY (webhook_id, seq)
);
