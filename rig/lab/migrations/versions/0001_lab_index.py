"""The lab index: runs, their instruments, criteria and calibration results.

Revision ID: 0001
Revises:
Create Date: 2026-11-25
"""

from __future__ import annotations

from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

UPGRADE = """
CREATE TABLE lab_runs (
    id bigserial PRIMARY KEY,
    run_uid text NOT NULL UNIQUE,          -- run id, a colon, data sha256: the idempotency key
    run_id text NOT NULL,                  -- the run folder's name
    rig text NOT NULL,                     -- [lab] rig of the run's configuration, else the host
    host text,
    procedure text,
    dut_serial text,
    lot text,                              -- the procedure parameter 'lot'
    operator text,
    status text NOT NULL,                  -- complete, failed, aborted, error, incomplete
    verdict text,                          -- PASS, FAIL or NULL (no acceptance check)
    started_at timestamptz,
    sealed_at timestamptz,
    software_version text,
    data_sha256 text,                      -- NULL: the run has no seal
    report_files text[] NOT NULL DEFAULT '{}',
    synced_at timestamptz NOT NULL DEFAULT now()
);
CREATE INDEX lab_runs_started ON lab_runs (started_at DESC, id DESC);
CREATE INDEX lab_runs_dut ON lab_runs (dut_serial, started_at);
CREATE INDEX lab_runs_status ON lab_runs (status, started_at DESC);
CREATE INDEX lab_runs_lot ON lab_runs (lot);
CREATE INDEX lab_runs_rig ON lab_runs (rig);
CREATE INDEX lab_runs_unsealed ON lab_runs (id) WHERE data_sha256 IS NULL;

CREATE TABLE lab_instruments (
    run bigint NOT NULL REFERENCES lab_runs (id) ON DELETE CASCADE,
    name text NOT NULL,
    kind text NOT NULL,
    serial text,
    calibrated_on date,
    certificate_expires date,
    expired boolean,                       -- expired at the run's start; NULL: no date known
    PRIMARY KEY (run, name)
);
CREATE INDEX lab_instruments_expired ON lab_instruments (run) WHERE expired;
CREATE INDEX lab_instruments_serial ON lab_instruments (serial);

CREATE TABLE lab_criteria (
    run bigint NOT NULL REFERENCES lab_runs (id) ON DELETE CASCADE,
    name text NOT NULL,
    value double precision,
    unit text NOT NULL DEFAULT '',
    min double precision,
    max double precision,
    margin double precision,               -- to the nearest limit, in unit; > 0 inside
    verdict text NOT NULL,
    PRIMARY KEY (run, name)
);
CREATE INDEX lab_criteria_failed ON lab_criteria (run) WHERE verdict = 'FAIL';

CREATE TABLE lab_results (
    run bigint NOT NULL REFERENCES lab_runs (id) ON DELETE CASCADE,
    source text NOT NULL,                  -- the calibration step's name
    name text NOT NULL,                    -- x0_ut, a, rho_deg, residual_rms_nt, ...
    value double precision NOT NULL,
    sigma double precision,                -- 1-sigma, same unit; NULL when not estimated
    PRIMARY KEY (run, source, name)
);
CREATE INDEX lab_results_name ON lab_results (name, run) INCLUDE (value, sigma);
"""


def upgrade() -> None:
    for statement in UPGRADE.split(";\n"):
        if statement.strip():
            op.execute(statement)


def downgrade() -> None:
    op.execute("DROP TABLE lab_results, lab_criteria, lab_instruments, lab_runs")
