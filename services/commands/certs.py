"""``slamlens certs DIR --name NAME [--name NAME …] [--host HOST …]`` (docs/security.md).

Creates or extends the small certificate authority in DIR (:mod:`slamlens.common.certs`) and prints
one line per identity it created, kept or re-issued, then what to copy where.
"""

from __future__ import annotations

import argparse

from slamlens.common.certs import CA_CERT, CA_KEY, extend_authority
from slamlens.common.config import settings_from_args
from slamlens.services.commands.settings import CertsSettings


def run(command: str, args: argparse.Namespace) -> int:
    s = settings_from_args(CertsSettings, args)
    for line in extend_authority(s.directory, s.names, hosts=s.hosts):
        print(line)
    print(f"copy {CA_CERT} and each NAME.pem + NAME.key to the machine that runs NAME; "
          f"{CA_KEY} stays here. A router needs every NAME.pem it must recognise.")
    return 0
