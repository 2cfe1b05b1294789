-- Tags by tag: `tag=` filters walk this index instead of scanning every episode's `tags` JSON with
-- LIKE. Tags are set at ingest and never change, so the ingest writes these rows with the
-- episodes. Filled here from the episodes already stored. Kept in step with the other backend's
-- history.
CREATE TABLE episode_tags (
    tag TEXT NOT NULL,
    episode_id TEXT NOT NULL,
    PRIMARY KEY (tag, episode_id)
) WITHOUT ROWID;
INSERT OR IGNORE INTO episode_tags (tag, episode_id)
SELECT DISTINCT j.value, e.id FROM episodes e, json_each(e.tags) j WHERE e.tags <> '[]';
