-- Evaluation runs: how an episode was produced (the base policy, or steered by best-of-N, classifier
-- guidance or flow guidance with a verifier artifact), with free-form tags. A run's id is derived
-- from its content, so ingesting more episodes of the same run reuses its row. Episodes ingested
-- without a run keep run_id NULL. Each version freezes its episode counts per policy, checkpoint,
-- task, run and label (version_run_counts, written with its label snapshot like version_counts):
-- the scoreboard reads a few rows of it. Versions written before this migration had no runs: their
-- counts come from version_counts. Kept in step with the sqlite history.
CREATE TABLE runs (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    steering TEXT NOT NULL,
    artifact_id TEXT,
    tags TEXT NOT NULL,
    created_at TEXT NOT NULL
);
CREATE INDEX runs_by_name ON runs (name);
ALTER TABLE episodes ADD COLUMN run_id TEXT REFERENCES runs(id);
CREATE TABLE version_run_counts (
    version BIGINT NOT NULL,
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    task TEXT NOT NULL,
    run_id TEXT NOT NULL,
    label TEXT NOT NULL,
    n BIGINT NOT NULL,
    PRIMARY KEY (version, policy, checkpoint, task, run_id, label)
);
INSERT INTO version_run_counts (version, policy, checkpoint, task, run_id, label, n)
    SELECT version, policy, checkpoint, task, '', label, n FROM version_counts;
