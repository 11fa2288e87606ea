"""Dependencies of the routers: the service objects built by the application's lifespan.

The routers receive them through FastAPI's dependency injection (``ServicesDep``), never as
module globals, so that an application instance owns its store, storage, queue, settings,
metrics and API keys, and tests can build one with other parts.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated

from fastapi import Depends, Request

from pwlreg.service.metrics import Metrics
from pwlreg.service.queue import JobQueue
from pwlreg.service.settings import Settings
from pwlreg.service.storage import Storage
from pwlreg.service.store import JobStore

if TYPE_CHECKING:
    from pwlreg.service.auth import ApiKeys
    from pwlreg.service.webhooks import Webhooks


@dataclass
class Services:
    """Everything the routers need, owned by one application instance."""

    settings: Settings
    store: JobStore
    storage: Storage
    queue: JobQueue
    metrics: Metrics
    api_keys: ApiKeys
    """The configured API keys (empty: open access, every caller is the anonymous client)."""
    webhooks: Webhooks | None = None
    """The webhook delivery loop (told when a job ends)."""


def get_services(request: Request) -> Services:
    """The services of the application serving ``request``."""
    return request.app.state.services


ServicesDep = Annotated[Services, Depends(get_services)]
