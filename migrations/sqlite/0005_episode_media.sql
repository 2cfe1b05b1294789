-- Where each camera's frames of an episode live, so serving an episode's video needs no steps file:
-- the video object and the time span of the episode's frames in it (LeRobot v3 packs many episodes
-- into one video). Filled at ingest commit; steps files written before this migration are indexed on
-- first use (`media_indexed` stays NULL until then). Kept in step with the other backend's history.
CREATE TABLE episode_media (
    episode_id TEXT NOT NULL REFERENCES episodes(id),
    media_key TEXT NOT NULL,
    path TEXT NOT NULL,
    start_seconds DOUBLE PRECISION NOT NULL,
    end_seconds DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (episode_id, media_key)
);
ALTER TABLE data_files ADD COLUMN media_indexed BIGINT;
