"""Dependencies of the routers: the service objects built by the application's lifespan.

The routers receive the store, the storage, the queue, the settings and the metrics through
FastAPI's dependency injection (``Annotated[..., Depends(...)]``), never as module globals.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request

from service.metrics import Metrics
from service.queue import JobQueue
from service.settings import Settings
from service.storage import LocalStorage
from service.store import JobStore


@dataclass
class Services:
    """Everything the routers need, owned by one application instance."""

    settings: Settings
    store: JobStore
    storage: LocalStorage
    queue: JobQueue
    metrics: Metrics


def get_services(request: Request) -> Services:
    return request.app.state.services


def get_settings(request: Request) -> Settings:
    return get_services(request).settings


def get_store(request: Request) -> JobStore:
    return get_services(request).store


def get_storage(request: Request) -> LocalStorage:
    return get_services(request).storage


def get_queue(request: Request) -> JobQueue:
    return get_services(request).queue


def get_metrics(request: Request) -> Metrics:
    return get_services(request).metrics


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[JobStore, Depends(get_store)]
StorageDep = Annotated[LocalStorage, Depends(get_storage)]
QueueDep = Annotated[JobQueue, Depends(get_queue)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
