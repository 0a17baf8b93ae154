"""Python clients of the server's protocol: sequence replay (demo session, tests, load tests)."""
