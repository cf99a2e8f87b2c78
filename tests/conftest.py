import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from netfixture import build_cross_net  # noqa: E402


@pytest.fixture(scope="session")
def cross_net(tmp_path_factory) -> Path:
    return build_cross_net(tmp_path_factory.mktemp("nets") / "cross")
