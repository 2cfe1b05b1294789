-- The review queue (issue 17): verifier scores of episodes, computed by a `score` job and stored
-- so listing the queue never runs a verifier. One row per (artifact, episode): the mean step
-- score and the per-step series (a JSON array of f32, one per step). Kept in step with the other
-- backend's history.
CREATE TABLE episode_scores (
    artifact_id TEXT NOT NULL,
    episode_id TEXT NOT NULL,
    score DOUBLE PRECISION NOT NULL,
    step_scores TEXT NOT NULL,
    job_id TEXT,
    created_at TEXT NOT NULL,
    PRIMARY KEY (artifact_id, episode_id)
);
CREATE INDEX episode_scores_by_episode ON episode_scores (episode_id);

-- The artifact that orders a policy's review queue (a campaign here is a policy). Without a row
-- an episode is scored by its checkpoint's `classifier@latest` alias.
CREATE TABLE review_artifacts (
    policy TEXT PRIMARY KEY,
    artifact_id TEXT NOT NULL,
    updated_by TEXT NOT NULL,
    updated_at TEXT NOT NULL
);
