import sys

from slamlens.services.commands.cli import main

sys.exit(main())
