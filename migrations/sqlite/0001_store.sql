-- Core store: versions, sources, episodes, labels. Kept in step with ../postgres/0001_store.sql.
CREATE TABLE store_head (id INTEGER PRIMARY KEY, version BIGINT NOT NULL);
INSERT INTO store_head (id, version) VALUES (1, 0);

CREATE TABLE versions (
    version BIGINT PRIMARY KEY,
    kind TEXT NOT NULL,
    message TEXT NOT NULL,
    actor TEXT NOT NULL,
    created_at TEXT NOT NULL,
    labels_path TEXT NOT NULL,
    source_sha256 TEXT,
    episodes_added BIGINT NOT NULL,
    episodes_removed BIGINT NOT NULL,
    labels_changed BIGINT NOT NULL,
    episode_count BIGINT NOT NULL
);

CREATE TABLE policies (name TEXT PRIMARY KEY, created_at TEXT NOT NULL);
CREATE TABLE checkpoints (
    policy TEXT NOT NULL REFERENCES policies(name),
    name TEXT NOT NULL,
    created_at TEXT NOT NULL,
    PRIMARY KEY (policy, name)
);
CREATE TABLE tasks (name TEXT PRIMARY KEY, created_at TEXT NOT NULL);

CREATE TABLE sources (
    sha256 TEXT PRIMARY KEY,
    path TEXT NOT NULL,
    format TEXT NOT NULL,
    size_bytes BIGINT NOT NULL,
    metadata TEXT NOT NULL,
    version BIGINT NOT NULL,
    created_at TEXT NOT NULL
);

CREATE TABLE data_files (
    path TEXT PRIMARY KEY,
    kind TEXT NOT NULL,
    size_bytes BIGINT NOT NULL,
    num_rows BIGINT NOT NULL,
    version_added BIGINT NOT NULL,
    version_removed BIGINT
);

CREATE TABLE media_objects (
    sha256 TEXT PRIMARY KEY,
    path TEXT NOT NULL,
    content_type TEXT NOT NULL,
    size_bytes BIGINT NOT NULL,
    version_added BIGINT NOT NULL
);

CREATE TABLE episodes (
    id TEXT PRIMARY KEY,
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    task TEXT,
    source_sha256 TEXT NOT NULL REFERENCES sources(sha256),
    source_name TEXT NOT NULL,
    source_index BIGINT NOT NULL,
    length BIGINT NOT NULL,
    tags TEXT NOT NULL,
    metadata TEXT NOT NULL,
    data_file TEXT NOT NULL REFERENCES data_files(path),
    row_group BIGINT NOT NULL,
    version_added BIGINT NOT NULL,
    version_removed BIGINT,
    label TEXT NOT NULL,
    label_source TEXT NOT NULL,
    label_revision BIGINT NOT NULL,
    label_actor TEXT NOT NULL,
    label_updated_at TEXT NOT NULL,
    created_at TEXT NOT NULL
);
CREATE INDEX episodes_by_checkpoint ON episodes (policy, checkpoint);

CREATE TABLE label_events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    episode_id TEXT NOT NULL REFERENCES episodes(id),
    revision BIGINT NOT NULL,
    old_label TEXT,
    new_label TEXT NOT NULL,
    source TEXT NOT NULL,
    actor TEXT NOT NULL,
    note TEXT,
    created_at TEXT NOT NULL,
    UNIQUE (episode_id, revision)
);

CREATE TABLE version_labels (
    version BIGINT NOT NULL,
    episode_id TEXT NOT NULL,
    label TEXT NOT NULL,
    label_source TEXT NOT NULL,
    revision BIGINT NOT NULL,
    PRIMARY KEY (version, episode_id)
);
