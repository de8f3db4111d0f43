import sys

from hbis_torch.cli import main

sys.exit(main())
