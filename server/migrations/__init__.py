"""Alembic migrations of the service database (``server/alembic.ini``)."""
