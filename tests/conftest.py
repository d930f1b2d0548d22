"""Shared fixtures: a real PostgreSQL server (session-scoped, started only when a test asks)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from _postgres import PostgresServer


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    server = PostgresServer().start()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(scope="module")
def no_jax_cache() -> Iterator[None]:
    """JAX's persistent compile cache off for the module (Dask workers started meanwhile inherit
    it): keeps the tests out of ~/.cache."""
    mp = pytest.MonkeyPatch()
    mp.setenv("EOL_CAL_JAX_CACHE", "off")
    yield
    mp.undo()


@pytest.fixture(params=["sqlite", "postgresql"])
def records_db(request, tmp_path: Path) -> str | Path:
    """A new, empty records database of each backend: a SQLite file path or a PostgreSQL URL."""
    if request.param == "sqlite":
        return tmp_path / "records.sqlite"
    server: PostgresServer = request.getfixturevalue("postgres_server")
    return server.create_db("r" + uuid.uuid4().hex[:12])
