"""Test-only stand-in for ROS 2 `launch` (see _impl.py and ../README.md); never installed."""
from . import actions, conditions, event_handlers, events, substitutions  # noqa: F401
from ._impl import (Action, Condition, Event, EventHandler, LaunchContext, LaunchDescription,  # noqa: F401
                    LaunchDescriptionEntity, LaunchService, Substitution, SubstitutionFailure)

SomeSubstitutionsType = object
