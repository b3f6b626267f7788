"""Fixtures of the recording tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from dyknow.transport import Session, make_config
from tests.conftest import free_port


@pytest.fixture
def listening() -> Iterator[tuple[Session, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Session(make_config(listen=[endpoint])) as session:
        yield session, endpoint
