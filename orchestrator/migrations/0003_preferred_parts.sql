-- A part that prefers a worker (the one that scored its brick, which may hold its kept top)
-- goes to that worker's lease first: its queued parts are found by worker, oldest first,
-- without scanning the queue.
CREATE INDEX jobs_queued_preferring ON jobs ((job->'spec'->'part'->>'prefer_worker'), id)
    WHERE state = 'queued';
