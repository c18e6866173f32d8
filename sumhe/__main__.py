from sumhe import cli

raise SystemExit(cli.main())
