"""Background jobs: the queue in the database, the kinds of job and what a running job sees."""
