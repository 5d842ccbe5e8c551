"""The RCM platform agent (``rcmp_n``): one Twisted process per machine of the platform.

Modules follow the original distribution's names; each module's docstring says what it owns (see
docs/DESIGN.md). ``rcmp_node.main`` is the entry point of both ``rcmp_n`` and ``python3 -m rcm_platform``.
"""
