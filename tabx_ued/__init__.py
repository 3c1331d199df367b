"""The command line of TABX-UED: the `tabx` command, composed from every layer's commands.

It is the top layer: `tabx` (simulator) <- `level_buffer` <- `ued` (learning) <- `workers`
(who runs what, where) <- `tabx_ued` (docs/architecture.md).
"""
