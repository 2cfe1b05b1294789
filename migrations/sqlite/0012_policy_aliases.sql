-- A policy's aliases (`prod`, `canary`): a name for one of its checkpoints, or one steered run of
-- it (CHECKPOINT/RUN: the run records the steering and the verifier artifact). A protected alias
-- moves only when the anytime-valid comparison of the new target against the current one has
-- decided "not worse" on every task; the comparison (version, counts, method, decision) is kept
-- as the move's evidence, in the alias row and in the append-only history of moves. `protected`
-- is 0 or 1. Kept in step with the postgres history.
CREATE TABLE policy_aliases (
    policy TEXT NOT NULL,
    alias TEXT NOT NULL,
    target TEXT NOT NULL,
    protected BIGINT NOT NULL,
    evidence TEXT,
    actor TEXT NOT NULL,
    updated_at TEXT NOT NULL,
    PRIMARY KEY (policy, alias)
);
CREATE TABLE policy_alias_moves (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    policy TEXT NOT NULL,
    alias TEXT NOT NULL,
    from_target TEXT,
    to_target TEXT NOT NULL,
    evidence TEXT,
    actor TEXT NOT NULL,
    created_at TEXT NOT NULL
);
CREATE INDEX policy_alias_moves_by_alias ON policy_alias_moves (policy, alias, id);
