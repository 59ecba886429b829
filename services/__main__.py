import sys

from slamlens.services.cli import main

sys.exit(main())
