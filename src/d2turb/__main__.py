import sys

from d2turb.cli import main

sys.exit(main())
