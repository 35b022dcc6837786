from relightcli.cli import main

raise SystemExit(main())
