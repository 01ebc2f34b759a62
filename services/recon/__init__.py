"""A reconstruction worker of the pool: pulls jobs from the trainer service, renders, publishes."""
