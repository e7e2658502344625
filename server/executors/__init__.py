"""Where jobs run: in the API process (``embedded``, the default) or on a Ray cluster (``ray``).

``CSA_EXECUTOR`` chooses; both run the same three phases of each job kind (``gather``,
``compute``, ``register``: ``server/jobs/phases.py``). See docs/architecture.md, "Executors".
"""

from __future__ import annotations

from server.executors.base import Executor
from server.services import Services


def make_executor(services: Services) -> Executor:
    """The executor ``services.settings.executor`` names (Ray is imported only for ``ray``)."""
    name = services.settings.executor
    if name == "ray":
        from server.executors.ray_cluster import RayExecutor

        return RayExecutor(services)
    from server.executors.embedded import EmbeddedExecutor

    return EmbeddedExecutor(services)
