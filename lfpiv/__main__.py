from lfpiv.cli import main

raise SystemExit(main())
