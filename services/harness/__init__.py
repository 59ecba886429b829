"""Helpers for the tests and benchmarks of a slamlens checkout: starting its processes
(``procs``), collecting what they publish (``collect``), hostile payloads (``fuzz``), two
hosts in network namespaces (``netns``), a web client (``web_client``), the MRCLAM pipeline
through the real processes (``mrclam_pipeline``). No service imports them."""
