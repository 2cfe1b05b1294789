-- Several labelers (issue 17). A campaign is a policy: how many labelers must agree on an
-- episode (1 = one verdict sets the label, as before) and whether they label blind. Each
-- labeler's verdict is an append-only vote; the episode's label moves (a label event, source
-- consensus or adjudication) only when enough votes agree or an adjudicator settles a dispute.
-- A failure-cause taxonomy per task ('*': tasks without their own). Label events and votes carry
-- data (JSON: failure_cause, spans). Kept in step with the other backend's history.
CREATE TABLE campaigns (
    policy TEXT PRIMARY KEY,
    labels_needed BIGINT NOT NULL,
    blind BIGINT NOT NULL,
    updated_by TEXT NOT NULL,
    updated_at TEXT NOT NULL
);
CREATE TABLE failure_causes (
    task TEXT PRIMARY KEY,
    causes TEXT NOT NULL,
    updated_by TEXT NOT NULL,
    updated_at TEXT NOT NULL
);
CREATE TABLE label_votes (
    id BIGSERIAL PRIMARY KEY,
    episode_id TEXT NOT NULL REFERENCES episodes(id),
    actor TEXT NOT NULL,
    label TEXT NOT NULL,
    data TEXT,
    note TEXT,
    created_at TEXT NOT NULL
);
CREATE INDEX label_votes_by_episode ON label_votes (episode_id, id);
ALTER TABLE label_events ADD COLUMN data TEXT;
