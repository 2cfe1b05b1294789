-- Lists that stay fast at a million episodes (store/README.md, "Catalog indexes and counts").
-- Kept in step with the other backend's history.
--
-- Keyset pages (`WHERE <filters> AND id > $cursor ORDER BY id LIMIT n`) read one index range in id
-- order when the filters' equality columns lead an index that ends in `id`. Label-dependent indexes
-- cover visible episodes only (the current state); the `--version N` path reads labels from
-- `version_labels` and uses the policy/checkpoint/task indexes, which therefore cover every row.
DROP INDEX episodes_by_checkpoint;
CREATE INDEX episodes_by_checkpoint_id ON episodes (policy, checkpoint, id);
CREATE INDEX episodes_by_policy_id ON episodes (policy, id);
CREATE INDEX episodes_by_task_id ON episodes (task, id);
CREATE INDEX episodes_visible_by_label ON episodes (label, id) WHERE version_removed IS NULL;
CREATE INDEX episodes_visible_by_policy_label ON episodes (policy, label, id) WHERE version_removed IS NULL;
CREATE INDEX episodes_visible_by_checkpoint_label ON episodes (policy, checkpoint, label, id) WHERE version_removed IS NULL;
CREATE INDEX episodes_visible_by_task_label ON episodes (task, label, id) WHERE version_removed IS NULL;
CREATE INDEX episodes_visible_by_label_source ON episodes (label_source, id) WHERE version_removed IS NULL;

-- Episode counts per (policy, checkpoint, task, label) of the visible episodes, maintained in the
-- same transaction as every label write, ingest and deletion. `task` is '' for episodes without
-- one (task names are never empty). A writer adds its deltas to one `shard` row per key, so
-- concurrent writers on Postgres rarely wait on the same row; a count is the sum over shards.
CREATE TABLE episode_counts (
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    task TEXT NOT NULL,
    label TEXT NOT NULL,
    shard BIGINT NOT NULL,
    n BIGINT NOT NULL,
    PRIMARY KEY (policy, checkpoint, task, label, shard)
);
INSERT INTO episode_counts (policy, checkpoint, task, label, shard, n)
SELECT policy, checkpoint, COALESCE(task, ''), label, 0, COUNT(*) FROM episodes
WHERE version_removed IS NULL GROUP BY policy, checkpoint, COALESCE(task, ''), label;

-- The same counts frozen per version (written with the version's label snapshot).
CREATE TABLE version_counts (
    version BIGINT NOT NULL,
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    task TEXT NOT NULL,
    label TEXT NOT NULL,
    n BIGINT NOT NULL,
    PRIMARY KEY (version, policy, checkpoint, task, label)
);
INSERT INTO version_counts (version, policy, checkpoint, task, label, n)
SELECT l.version, e.policy, e.checkpoint, COALESCE(e.task, ''), l.label, COUNT(*)
FROM version_labels l JOIN episodes e ON e.id = l.episode_id
GROUP BY l.version, e.policy, e.checkpoint, COALESCE(e.task, ''), l.label;
