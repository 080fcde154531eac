"""sdfrd's configuration: its options, one definition each (`options`), read from defaults,
a TOML file and flags (`load`), and the fleet keys on disk (`keystore`)."""
