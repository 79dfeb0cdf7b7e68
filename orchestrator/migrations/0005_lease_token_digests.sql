-- A running lease's token is kept as the SHA-256 of its secret (32 bytes), so that reading the
-- store gives nothing that acts on a lease; the orchestrator hashes a presented token and
-- compares. Tokens stored by earlier builds (the 16-byte secret itself) are hashed here.
UPDATE jobs SET lease_token = sha256(lease_token) WHERE length(lease_token) = 16;
COMMENT ON COLUMN jobs.lease_token IS
    'SHA-256 of the running lease''s secret token (NULL when no lease runs)';
