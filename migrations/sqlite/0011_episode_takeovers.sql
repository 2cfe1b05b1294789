-- Human takeovers (LeRobot's DAgger `intervention` frames, or a source's flag named by
-- `--intervention-key`): the first step a human controlled and how many steps they controlled,
-- from the episode's `intervention` steps column. Both NULL when the source records no takeovers;
-- first_intervention alone NULL when it records them and none happened. Splits train on the steps
-- before first_intervention and report that share per checkpoint. Existing episodes had no such
-- column: NULL. Kept in step with the postgres history.
ALTER TABLE episodes ADD COLUMN first_intervention BIGINT;
ALTER TABLE episodes ADD COLUMN intervention_steps BIGINT;
