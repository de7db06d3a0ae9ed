import sys

from thermod.cli import main

if __name__ == "__main__":   # a spawned solver child imports this module too
    sys.exit(main())
