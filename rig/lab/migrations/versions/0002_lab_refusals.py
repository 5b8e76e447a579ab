"""Runs the index refused: changed since they were sealed, or not storable (issue 29).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-25
"""

from __future__ import annotations

from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None

UPGRADE = """
CREATE TABLE lab_refusals (
    run_uid text NOT NULL,                 -- run id, a colon, the data sha256 of its seal
    run_id text NOT NULL,
    rig text,
    host text,
    kind text NOT NULL,                    -- 'changed since sealed' or 'cannot be stored'
    reason text NOT NULL,                  -- one line: what differs, or PostgreSQL's reason
    sealed_sha256 text,                    -- the seal's data sha256 (NULL: the run has no seal)
    first_at timestamptz NOT NULL DEFAULT now(),
    last_at timestamptz NOT NULL DEFAULT now(),
    attempts integer NOT NULL DEFAULT 1,   -- syncs that refused it
    PRIMARY KEY (run_uid, kind)
);
CREATE INDEX lab_refusals_last ON lab_refusals (last_at DESC);
"""


def upgrade() -> None:
    for statement in UPGRADE.split(";\n"):
        if statement.strip():
            op.execute(statement)


def downgrade() -> None:
    op.execute("DROP TABLE lab_refusals")
