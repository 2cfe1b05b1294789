-- Derived per-step data ("layers"): a named per-step float32 vector (e.g. the policy encoder's
-- features of each step's camera frame) attached to existing episodes by (episode_id, t), made by
-- a producer (a JSON object: encoder, policy checkpoint, content hash) identified by its sha256.
-- Layer values live in their own Parquet files (data_files.kind = 'layer'); the steps files are
-- never rewritten. An episode holds at most one current row per layer name: a new producer's
-- values replace the old ones from the version that writes them (time travel keeps both).
-- Kept in step with the other backend's history.
CREATE TABLE layers (
    name TEXT NOT NULL,
    producer_hash TEXT NOT NULL,
    producer TEXT NOT NULL,
    dim BIGINT NOT NULL,
    version_added BIGINT NOT NULL,
    created_at TEXT NOT NULL,
    PRIMARY KEY (name, producer_hash)
);
CREATE TABLE episode_layers (
    layer TEXT NOT NULL,
    episode_id TEXT NOT NULL REFERENCES episodes(id),
    producer_hash TEXT NOT NULL,
    data_file TEXT NOT NULL REFERENCES data_files(path),
    row_group BIGINT NOT NULL,
    row_offset BIGINT NOT NULL,
    row_count BIGINT NOT NULL,
    version_added BIGINT NOT NULL,
    version_removed BIGINT,
    PRIMARY KEY (layer, episode_id, version_added)
);
CREATE INDEX episode_layers_by_episode ON episode_layers (episode_id, layer);
CREATE INDEX episode_layers_by_producer ON episode_layers (layer, producer_hash);
CREATE UNIQUE INDEX episode_layers_current ON episode_layers (layer, episode_id) WHERE version_removed IS NULL;
