"""Human-study tasks and their launcher."""
