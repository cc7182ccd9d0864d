"""Tables, charts and sheets made only from result records (never by re-running anything)."""
