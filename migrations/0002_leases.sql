-- Leases: a claimed job belongs to one worker for as long as that worker renews
-- its lease. `lease_token` is new at every claim and fences every write of the attempt;
-- `lease_expires_ms` is the database clock (ms since 1970) after which another worker
-- may take the job back; `worker` names the claimer (host:pid), for operators.
ALTER TABLE jobs ADD COLUMN lease_token TEXT;
ALTER TABLE jobs ADD COLUMN lease_expires_ms INTEGER;
ALTER TABLE jobs ADD COLUMN worker TEXT;
