"""The lab index: a shared PostgreSQL database of every closed run of every rig (optional).

Each run stays a folder with its own SQLite store, the record; the index holds a summary of each
sealed run (procedure, rig, DUT, lot, operator, instruments with their certificates, status,
verdict, criteria with margins, calibration results with sigma, data hash, report files) so a lab
can ask across runs and rigs. :mod:`rig.lab.sync` pushes runs (idempotent: the key is the run id
plus the data hash), :mod:`rig.lab.queries` answers, :mod:`rig.lab.schema` keeps the schema at
its newest migration. psycopg and alembic are imported only when the index is used.
"""
