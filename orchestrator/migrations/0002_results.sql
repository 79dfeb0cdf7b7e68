-- Results of the parts of bricked jobs (a brick's score summary or file), kept until the
-- bricked job is done with them.
CREATE TABLE results (
    parent BIGINT NOT NULL,
    job_id BIGINT NOT NULL,
    data   BYTEA  NOT NULL,
    PRIMARY KEY (parent, job_id)
);
