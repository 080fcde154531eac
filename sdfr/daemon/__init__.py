"""Process-level adapters: the supervisor and the two layers it runs."""
