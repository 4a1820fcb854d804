import sys

from bubble_rt.cli import main

sys.exit(main())
