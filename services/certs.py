"""``slamlens certs DIR --name NAME [--name NAME …] [--host HOST …]`` (SPEC §7b).

Creates or extends the small certificate authority in DIR (:mod:`common.certs`) and prints
one line per file set it created, kept or re-issued, then what to copy where.
"""

from __future__ import annotations

import argparse

from common.certs import CA_CERT, CA_KEY


def add_arguments(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument("directory", metavar="DIR", help="folder of the authority (created 0700)")
    parser.add_argument("--name", action="append", default=[], required=True, metavar="NAME",
                        help="identity to issue (repeatable): robot-R, camera-C, monitor-R, "
                             "viewer-…, router-…; existing ones are kept")
    parser.add_argument("--host", action="append", default=[], metavar="HOST",
                        help="DNS name or IP address clients dial a router at (repeatable); "
                             "added to the router-… certificates")


def run(command: str, args: argparse.Namespace) -> int:
    from common.certs import extend_authority

    for line in extend_authority(args.directory, args.name, hosts=args.host):
        print(line)
    print(f"copy {CA_CERT} and each NAME.pem + NAME.key to the machine that runs NAME; "
          f"{CA_KEY} stays here. A router needs every NAME.pem it must recognise.")
    return 0
