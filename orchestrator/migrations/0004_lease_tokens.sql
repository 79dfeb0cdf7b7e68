-- The secret of each running lease (16 random bytes, drawn when the lease is granted; NULL when
-- no lease runs). Kept in a column of its own, never in the `job` record, which operators and
-- tools read: whoever presents it is the lease's holder.
ALTER TABLE jobs ADD COLUMN IF NOT EXISTS lease_token BYTEA;

-- A bricked job's parts by their parent: ending the parent (done, failed, cancelled) cancels its
-- live parts in the same transaction.
CREATE INDEX IF NOT EXISTS jobs_parts ON jobs (((job->'spec'->'part'->>'parent')::bigint))
    WHERE job->'spec' ? 'part';
