"""Every malformed payload of services/harness/fuzz.py is refused with MessageError, never a
crash."""

from __future__ import annotations

import numpy as np
import pytest

from slamlens.common.errors import MessageError
from slamlens.common.messages import MESSAGE_TYPES
from slamlens.services.harness.fuzz import bad_payloads, field_breakers, valid


@pytest.mark.parametrize("kind", MESSAGE_TYPES, ids=lambda k: k.__name__)
def test_every_broken_payload_is_one_message_error(kind) -> None:
    assert kind.from_bytes(valid(kind).to_bytes()) == valid(kind)  # the template is valid
    rng = np.random.default_rng(1)
    payloads = list(bad_payloads(kind, rng, 3000))
    for payload in payloads:
        with pytest.raises(MessageError):
            kind.from_bytes(payload)


@pytest.mark.parametrize("kind", MESSAGE_TYPES, ids=lambda k: k.__name__)
def test_each_field_breaker_alone_is_refused(kind) -> None:
    import msgpack

    template = valid(kind).to_dict()
    for name, value in field_breakers(kind):
        broken = dict(template)
        if value is None:
            broken.pop(name)
        else:
            broken[name] = value
        with pytest.raises(MessageError):
            kind.from_bytes(msgpack.packb(broken, use_bin_type=True))
