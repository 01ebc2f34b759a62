"""A reconstruction worker of the pool: pulls jobs from the dispatcher, renders, publishes."""
