import sys

from wl.cli import main

sys.exit(main())
