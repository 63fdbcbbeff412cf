from wbc_jax.cli import main

raise SystemExit(main())
