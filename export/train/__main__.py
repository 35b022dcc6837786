import sys

from export.train.cli import main

sys.exit(main())
