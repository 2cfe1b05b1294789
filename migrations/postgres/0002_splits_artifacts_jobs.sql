-- Splits, verifier artifacts with aliases, training/ingest jobs. Kept in step with ../sqlite/.
CREATE TABLE splits (
    id TEXT PRIMARY KEY,
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    mode TEXT NOT NULL,
    source_checkpoints TEXT NOT NULL,
    version BIGINT NOT NULL,
    val_fraction DOUBLE PRECISION NOT NULL,
    seed BIGINT NOT NULL,
    train_episodes BIGINT NOT NULL,
    val_episodes BIGINT NOT NULL,
    created_by TEXT NOT NULL,
    created_at TEXT NOT NULL
);

CREATE TABLE split_episodes (
    split_id TEXT NOT NULL REFERENCES splits(id),
    episode_id TEXT NOT NULL,
    part TEXT NOT NULL,
    label TEXT NOT NULL,
    PRIMARY KEY (split_id, episode_id)
);

CREATE TABLE artifacts (
    id TEXT PRIMARY KEY,
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    kind TEXT NOT NULL,
    split_id TEXT,
    job_id TEXT,
    prefix TEXT NOT NULL,
    files TEXT NOT NULL,
    config TEXT NOT NULL,
    created_at TEXT NOT NULL
);
CREATE INDEX artifacts_by_checkpoint ON artifacts (policy, checkpoint, kind);

CREATE TABLE artifact_aliases (
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    kind TEXT NOT NULL,
    alias TEXT NOT NULL,
    artifact_id TEXT NOT NULL REFERENCES artifacts(id),
    updated_at TEXT NOT NULL,
    PRIMARY KEY (policy, checkpoint, kind, alias)
);

CREATE TABLE jobs (
    id TEXT PRIMARY KEY,
    kind TEXT NOT NULL,
    state TEXT NOT NULL,
    spec TEXT NOT NULL,
    progress TEXT NOT NULL,
    result TEXT,
    error TEXT,
    attempts BIGINT NOT NULL,
    max_attempts BIGINT NOT NULL,
    worker TEXT,
    lease_until_ms BIGINT,
    cancel_requested BIGINT NOT NULL,
    created_by TEXT NOT NULL,
    created_at TEXT NOT NULL,
    updated_at TEXT NOT NULL
);
CREATE INDEX jobs_by_state ON jobs (state, created_at);

CREATE TABLE tokens (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    role TEXT NOT NULL,
    token_hash TEXT NOT NULL UNIQUE,
    created_at TEXT NOT NULL,
    revoked_at TEXT
);
