-- Several episodes share one Parquet row group: each episode's rows are `row_count` rows starting at
-- `row_offset` inside row group `row_group` of `data_file`. Stores written before this migration hold
-- one row group per episode, so the backfill (offset 0, count = length) is exact for them.
-- Kept in step with the other backend's history.
ALTER TABLE episodes ADD COLUMN row_offset BIGINT;
ALTER TABLE episodes ADD COLUMN row_count BIGINT;
UPDATE episodes SET row_offset = 0, row_count = length WHERE row_offset IS NULL;
