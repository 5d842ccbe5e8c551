"""The RCM platform agent (``rcmp_n``): one Twisted process per machine of the platform.

The original distribution's modules keep their names and jobs; a job they have no home for has a module of its own
(``rcmp_config``, ``rcmp_log_guard``, ``rcmp_process``, ``rcmp_service_item``, ``rcmp_vpn``, ``rcmp_console``). Each
module's docstring says what it owns; docs/DESIGN.md maps them. ``rcmp_node.main`` is the entry point of both
``rcmp_n`` and ``python3 -m rcm_platform``.
"""
