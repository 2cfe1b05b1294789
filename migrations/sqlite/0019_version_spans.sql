-- Versions cost what they change. Until now every version copied every visible
-- episode's label into `version_labels`, and its counts into `version_counts` and
-- `version_run_counts`: a label snapshot of 10 changes in a 10^6-episode store wrote 10^6 rows.
-- Now a row holds for a span of versions, [version_from, version_to), and version_to is NULL while
-- it still holds at the head. A version closes the spans of the episodes (and count groups) it
-- changes and opens new ones, so it writes O(changed) rows; "the labels of version N" are the rows
-- whose span covers N, and an episode has a covering label span exactly while it is visible.
-- `episodes.label_frozen_revision` is the revision the head's open span holds; the partial index
-- finds the episodes whose label changed since without reading the others. Kept in step with the
-- postgres history.
ALTER TABLE episodes ADD COLUMN label_frozen_revision BIGINT;

CREATE TABLE version_label_spans (
    episode_id TEXT NOT NULL,
    version_from BIGINT NOT NULL,
    version_to BIGINT,
    label TEXT NOT NULL,
    label_source TEXT NOT NULL,
    revision BIGINT NOT NULL,
    PRIMARY KEY (episode_id, version_from)
);
-- A revision's versions are contiguous (revisions only grow, and an episode is visible from its
-- ingest to its removal): one span each.
INSERT INTO version_label_spans (episode_id, version_from, version_to, label, label_source, revision)
SELECT episode_id, MIN(version), MAX(version) + 1, MIN(label), MIN(label_source), revision
FROM version_labels GROUP BY episode_id, revision;
UPDATE version_label_spans SET version_to = NULL
WHERE version_to = (SELECT version + 1 FROM store_head WHERE id = 1);
UPDATE episodes SET label_frozen_revision =
    (SELECT s.revision FROM version_label_spans s WHERE s.episode_id = episodes.id AND s.version_to IS NULL);
DROP TABLE version_labels;
ALTER TABLE version_label_spans RENAME TO version_labels;
CREATE INDEX episodes_labels_unfrozen ON episodes (id)
    WHERE version_removed IS NULL AND (label_frozen_revision IS NULL OR label_frozen_revision <> label_revision);
CREATE INDEX episodes_removed_in ON episodes (version_removed) WHERE version_removed IS NOT NULL;

CREATE TABLE version_count_spans (
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    task TEXT NOT NULL,
    label TEXT NOT NULL,
    version_from BIGINT NOT NULL,
    version_to BIGINT,
    n BIGINT NOT NULL,
    PRIMARY KEY (policy, checkpoint, task, label, version_from)
);
INSERT INTO version_count_spans (policy, checkpoint, task, label, version_from, version_to, n)
SELECT policy, checkpoint, task, label, version,
       CASE WHEN version = (SELECT version FROM store_head WHERE id = 1) THEN NULL ELSE version + 1 END, n
FROM version_counts;
DROP TABLE version_counts;
ALTER TABLE version_count_spans RENAME TO version_counts;

CREATE TABLE version_run_count_spans (
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    task TEXT NOT NULL,
    run_id TEXT NOT NULL,
    label TEXT NOT NULL,
    version_from BIGINT NOT NULL,
    version_to BIGINT,
    n BIGINT NOT NULL,
    PRIMARY KEY (policy, checkpoint, task, run_id, label, version_from)
);
INSERT INTO version_run_count_spans (policy, checkpoint, task, run_id, label, version_from, version_to, n)
SELECT policy, checkpoint, task, run_id, label, version,
       CASE WHEN version = (SELECT version FROM store_head WHERE id = 1) THEN NULL ELSE version + 1 END, n
FROM version_run_counts;
DROP TABLE version_run_counts;
ALTER TABLE version_run_count_spans RENAME TO version_run_counts;

-- A version's labels file holds the rows it changed ('delta', with removed episodes flagged) or,
-- for versions written before this migration, all of them ('full'). A full file of a later
-- version, written after its commit to keep chains of deltas short, is its `labels_checkpoint`.
ALTER TABLE versions ADD COLUMN labels_kind TEXT NOT NULL DEFAULT 'full';
ALTER TABLE versions ADD COLUMN labels_checkpoint TEXT;
