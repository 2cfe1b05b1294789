-- Objects a writer has uploaded, or decided to re-use, before its version commits. gc skips them
-- (rows older than a day are a crashed writer's and no longer protect anything); the commit
-- deletes its writer's rows in the same transaction that makes the objects referenced.
-- Kept in step with the other backend's history.
CREATE TABLE pending_objects (
    path TEXT NOT NULL,
    writer TEXT NOT NULL,
    created_ms BIGINT NOT NULL,
    PRIMARY KEY (path, writer)
);
CREATE INDEX pending_objects_writer ON pending_objects (writer);
