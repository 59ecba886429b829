"""Key builders: the input key expression covers both input keys and nothing else."""

from __future__ import annotations

import inspect

import zenoh

from slamlens.common.keys import INPUT_LEAF_START, ROBOT_LEAVES, Keys


def _robot_keys(keys: Keys) -> dict[str, str]:
    """Every key a ``Keys`` method builds for one robot (methods taking only ``robot``)."""
    out = {}
    for name, method in inspect.getmembers(keys, inspect.ismethod):
        params = list(inspect.signature(method).parameters)
        if params == ["robot"] and name != "inputs":
            key = method("r1")
            if key.startswith(f"{keys.prefix}/robot/r1/"):
                out[name] = key
    return out


def test_every_robot_leaf_is_listed() -> None:
    keys = Keys()
    leaves = {k.removeprefix("slamlens/robot/r1/") for k in _robot_keys(keys).values()}
    assert leaves == set(ROBOT_LEAVES)


def test_the_input_expression_matches_exactly_the_two_input_keys() -> None:
    keys = Keys(prefix="lab/a")
    expr = zenoh.KeyExpr(keys.inputs("r1"))
    matched = {name for name, key in _robot_keys(keys).items()
               if expr.intersects(zenoh.KeyExpr(key))}
    assert matched == {"odometry", "observations"}
    assert not expr.intersects(zenoh.KeyExpr(keys.odometry("r2")))
    assert [leaf for leaf in ROBOT_LEAVES if leaf.startswith(INPUT_LEAF_START)] == [
        "odometry", "observations"]
