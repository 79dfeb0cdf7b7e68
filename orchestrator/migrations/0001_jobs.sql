-- The orchestrator's queue. `job` holds the whole record (the same JSON the embedded store
-- keeps); the other columns are derived from it on every write, so that the queue's queries
-- use indexes and operators can read job states with psql.
CREATE TABLE jobs (
    id               BIGSERIAL PRIMARY KEY,
    dedup_key        TEXT    NOT NULL UNIQUE,
    name             TEXT    NOT NULL,
    state            TEXT    NOT NULL,
    not_before_ms    BIGINT,
    lease_expires_ms BIGINT,
    worker           TEXT,
    attempts         INTEGER NOT NULL,
    error            TEXT,
    sha256           BYTEA   NOT NULL,
    upload           BOOLEAN NOT NULL,
    created_ms       BIGINT  NOT NULL,
    updated_ms       BIGINT  NOT NULL,
    job              JSONB   NOT NULL
);

-- Leasing scans queued jobs oldest first; reaping finds lapsed leases.
CREATE INDEX jobs_queued ON jobs (id) WHERE state = 'queued';
CREATE INDEX jobs_running ON jobs (lease_expires_ms) WHERE state = 'running';
-- When nothing is runnable, a worker is told when the next backoff ends.
CREATE INDEX jobs_backing_off ON jobs (not_before_ms) WHERE state = 'queued';
CREATE INDEX jobs_sha256 ON jobs (sha256) WHERE upload;

-- Uploaded sources, content-addressed, in chunks (a bytea value is limited to 1 GB and is
-- read whole; chunks keep memory per row small).
CREATE TABLE uploads (
    sha256 BYTEA   NOT NULL,
    seq    INTEGER NOT NULL,
    data   BYTEA   NOT NULL,
    PRIMARY KEY (sha256, seq)
);
