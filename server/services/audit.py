"""Reading the audit log of writes (``/api/v1/audit``, the dashboard's audit page); its
entries are written by ``server/audit.py``'s middleware."""

from __future__ import annotations

from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session

from server.db.models import AuditEntry

# Newest first: ids grow with time (the sort key of :func:`audit_query`, descending).
ORDER = (AuditEntry.id,)


def audit_query(key_name: str | None = None, method: str | None = None) -> Select:
    """The entries (of the key named ``key_name``, of ``method``), newest first."""
    query = select(AuditEntry).order_by(AuditEntry.id.desc())
    if key_name is not None:
        query = query.where(AuditEntry.key_name == key_name)
    if method is not None:
        query = query.where(AuditEntry.method == method.upper())
    return query


def entries_page(
    db: Session, key_name: str | None, offset: int, limit: int
) -> tuple[list[AuditEntry], int]:
    """``limit`` entries (of the key named ``key_name``) from ``offset`` on, newest first, and
    the number of all of them."""
    query = audit_query(key_name)
    total = db.scalar(select(func.count()).select_from(query.order_by(None).subquery())) or 0
    return list(db.scalars(query.limit(limit).offset(offset))), total
