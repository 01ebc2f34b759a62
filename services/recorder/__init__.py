"""The recorder service: every run on record, as MCAP (docs/recording.md)."""
