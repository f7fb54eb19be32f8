"""A landing's bag, recorded inside the pilot station's process (bag_record's node on the station's executor)."""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from rclpy.node import Node
from rclpy.parameter import Parameter

from assist_bags.bagio import BagError
from assist_bags.record_node import BagRecordNode


class LandingRecorder(BagRecordNode):
    """bag_record's node, but a write error stops only this recording (the station goes on; the row is kept)."""

    exit_on_write_error = False


def open_landing_bag(station: Node, output: str, topics: Sequence[str] = ()) -> LandingRecorder:
    """Start recording `topics` (empty: the contract set) into the new bag `output`, on the station's executor."""
    overrides = [Parameter('output', value=str(output)), Parameter('use_sim_time', value=True),
                 Parameter('split_duration_s', value=0.0), Parameter('discovery_period_s', value=0.25)]
    if topics:
        overrides.append(Parameter('topics', value=list(topics)))
    rec = LandingRecorder(parameter_overrides=overrides, cli_args=['--ros-args', '-r', '__node:=study_bag_record'],
                          context=station.context)
    station.executor.add_node(rec)
    return rec


def close_landing_bag(station: Node, rec: Any) -> None:
    """Stop and close a landing's bag (every message received so far kept)."""
    executor = station.executor
    if executor is not None:
        executor.remove_node(rec)
    try:
        rec.close()
    finally:
        rec.destroy_node()
    if rec.failure is not None:
        raise BagError(rec.failure)
