"""The node side of the runtime: the modules that run inside an instrumented node's process.

``rory_runtime.checkpointed`` and ``rory_runtime.checkpoint_module`` load them (through
:mod:`.attach`, the front door) only when a supervisor started the node. They never import the
supervisor (``rory_runtime.supervisor``), and its modules never import them: the zygote loads
:mod:`.attach` by name (``preload``) so that the nodes it forks find it loaded. What both sides
stand on (the protocol, the store, the codec, the log, ...) is beside this package, at
``rory_runtime``'s top level.

This package's ``__init__`` imports nothing, so that loading one of its modules loads only what
that module needs.
"""
