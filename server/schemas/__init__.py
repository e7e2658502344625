"""Pydantic request and response bodies, one module per resource (separate from the ORM)."""
