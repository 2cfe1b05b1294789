-- Failure monitors: a threshold on a verifier artifact's per-step scores, calibrated by split
-- conformal prediction on a checkpoint's successful episodes (verifier/src/monitor.rs). A monitor
-- is immutable and content-addressed (id = the first 16 hex digits of sha256 of `record`, the
-- record's JSON as its calibration wrote it); `evaluation` is what the calibration measured on
-- the held-out episodes. Aliases per (policy, checkpoint), like the artifacts' (`latest` moves
-- on every calibration). Kept in step with the other backend's history.
CREATE TABLE monitors (
    id TEXT PRIMARY KEY,
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    artifact_id TEXT NOT NULL REFERENCES artifacts(id),
    alpha DOUBLE PRECISION NOT NULL,
    threshold DOUBLE PRECISION NOT NULL,
    record TEXT NOT NULL,
    evaluation TEXT,
    created_by TEXT NOT NULL,
    created_at TEXT NOT NULL
);
CREATE INDEX monitors_by_checkpoint ON monitors (policy, checkpoint, created_at);
CREATE INDEX monitors_by_artifact ON monitors (artifact_id);
CREATE TABLE monitor_aliases (
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    alias TEXT NOT NULL,
    monitor_id TEXT NOT NULL REFERENCES monitors(id),
    updated_at TEXT NOT NULL,
    PRIMARY KEY (policy, checkpoint, alias)
);
