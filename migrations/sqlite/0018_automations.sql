-- Automations: rules declared per policy that turn the change feed into jobs (store/src/
-- automations.rs, run by the servers in api/src/automations.rs). Kept in step with the other
-- backend's history.
--
-- An automation is a cursor into `events` like a webhook: a server that holds its lease reads the
-- events after `cursor_seq`, updates the state of each target the rule watches (a checkpoint, or a
-- run) in `automation_targets`, and in the same transaction queues the jobs the rule fires, records
-- an `automation.fired` event for each and moves the cursor. So an event fires a rule at most once,
-- and a restart loses nothing.
CREATE TABLE automations (
    id TEXT PRIMARY KEY,
    policy TEXT NOT NULL,
    rule TEXT NOT NULL,
    params TEXT NOT NULL,
    cursor_seq BIGINT NOT NULL,
    fired BIGINT NOT NULL,
    lease_owner TEXT,
    lease_until_ms BIGINT NOT NULL,
    created_by TEXT NOT NULL,
    created_at TEXT NOT NULL
);
-- Per target: the last event that changed what the rule counts (`changed_seq`), the feed position a
-- verifier covers (`covered_seq`: the freeze of its split), the last on-policy split frozen
-- (`split_id`, `split_seq`), and the last firing (`fired_seq`, `job_id`).
CREATE TABLE automation_targets (
    automation_id TEXT NOT NULL REFERENCES automations(id) ON DELETE CASCADE,
    target TEXT NOT NULL,
    changed_seq BIGINT NOT NULL,
    covered_seq BIGINT NOT NULL,
    split_id TEXT,
    split_seq BIGINT NOT NULL,
    fired_seq BIGINT NOT NULL,
    job_id TEXT,
    PRIMARY KEY (automation_id, target)
);
-- "Are a run's episodes all labeled?" reads one run's episodes.
CREATE INDEX episodes_by_run ON episodes (run_id);
