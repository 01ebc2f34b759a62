"""Tests of the services' pure parts on their own (no bus, no server): each service's core.py,
the ingest core, the metrics ledger, and the services/kit parts they share."""
