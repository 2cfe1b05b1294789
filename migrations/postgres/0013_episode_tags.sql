-- Tags by tag: `tag=` filters walk this index instead of scanning every episode's `tags` JSON with
-- LIKE. Tags are set at ingest and never change, so the ingest writes these rows with the
-- episodes. Filled here from the episodes already stored. Kept in step with the other backend's
-- history.
CREATE TABLE episode_tags (
    tag TEXT NOT NULL,
    episode_id TEXT NOT NULL,
    PRIMARY KEY (tag, episode_id)
);
INSERT INTO episode_tags (tag, episode_id)
SELECT DISTINCT t.tag, e.id FROM episodes e, jsonb_array_elements_text(e.tags::jsonb) AS t(tag)
WHERE e.tags <> '[]'
ON CONFLICT DO NOTHING;
