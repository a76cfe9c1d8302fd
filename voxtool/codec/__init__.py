"""Map-change packets (seed: ogm-sync-hilbert.md): Hilbert order, packet bytes, logs, fusion."""
