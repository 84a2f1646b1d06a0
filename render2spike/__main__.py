import sys

from render2spike.cli import main

sys.exit(main())
