"""alembic's environment for the lab index: migrations run on the connection the caller passes
(:func:`rig.lab.schema.ensure_schema`), inside its transaction; no offline (SQL script) mode."""

from __future__ import annotations

from alembic import context

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=None, transactional_ddl=True)
with context.begin_transaction():
    context.run_migrations()
