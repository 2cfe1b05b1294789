-- The review orders from an index. Each episode carries `review_score`, its stored score by its
-- current review artifact (the policy's setting, else its checkpoint's classifier@latest), kept
-- by every write that changes it (scores stored, the setting, the alias moving), so
-- `order=uncertain|disagreement` pages of a policy walk these indexes on the order's key like the
-- id order walks the primary key. The key expressions are the ones `review.rs` orders by, to the
-- character. Kept in step with the other backend's history.
ALTER TABLE episodes ADD COLUMN review_score DOUBLE PRECISION;
UPDATE episodes SET review_score = (
    SELECT s.score FROM episode_scores s WHERE s.episode_id = episodes.id AND s.artifact_id = COALESCE(
        (SELECT ra.artifact_id FROM review_artifacts ra WHERE ra.policy = episodes.policy),
        (SELECT aa.artifact_id FROM artifact_aliases aa WHERE aa.policy = episodes.policy
            AND aa.checkpoint = episodes.checkpoint AND aa.kind = 'classifier' AND aa.alias = 'latest')))
WHERE id IN (SELECT episode_id FROM episode_scores);
CREATE INDEX episodes_review_uncertain ON episodes
    (policy, (COALESCE(ABS(review_score - 0.5), 9.0)), id) WHERE version_removed IS NULL;
CREATE INDEX episodes_review_disagreement ON episodes
    (policy, (CASE WHEN review_score IS NULL THEN 9.0 WHEN label = 'success' THEN review_score - 1.0
     WHEN label = 'failure' THEN 0.0 - review_score ELSE 8.0 END), id) WHERE version_removed IS NULL;
