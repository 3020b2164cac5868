"""services: the running product (configuration, messages, daemon, command line, evaluations)."""
