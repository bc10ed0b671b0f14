"""A short episode recorded to a ROS 2 bag with sqlite3 storage reads back with no bad message (the
bad-input cases: ``tests/unit/test_bad_input_bags.py``)."""
from __future__ import annotations

import pytest

from testbed.bags import BagReader


@pytest.mark.slow
def test_record_with_sqlite3_storage_writes_a_readable_bag(tmp_path):
    from testbed.record import record_episode

    bag_path = tmp_path / "rec_sqlite"
    record_episode(None, str(bag_path), "ros2", "sqlite3", 1, 1.5, None)
    assert any(p.suffix == ".db3" for p in bag_path.iterdir())
    with BagReader(bag_path) as bag:
        assert len(list(bag.scans())) >= 5 and not bag.bad_message_summary()
