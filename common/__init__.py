"""The shared contract of slamlens: messages, keys, bus, configuration and geometry.

Nothing in ``common`` imports from ``services``; every service imports from here.
"""
