"""`python -m sdfr.daemon`: sdfrd (see `sdfr.daemon.main`)."""

from sdfr.daemon import main

raise SystemExit(main())
