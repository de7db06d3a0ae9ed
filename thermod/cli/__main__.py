import sys

from thermod.cli import main

sys.exit(main())
