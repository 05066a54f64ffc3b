"""``dct-hil tcu`` and ``python -m tcu_stub.command``: the reference TCU as a
CAN node, the C node (``tcu_stub.c_node``, ``--impl c``, the default) or the
Python one (``tcu_stub.can_tcu``, ``--impl python``, for editing
``tcu_stub/logic.py``); the options and the run are ``tcu_stub.can_tcu``'s.
"""

import sys

from tcu_stub import can_tcu

__all__ = ["main", "run"]


def _c_opener(priority):
    from tcu_stub.c_node import DEFAULT_PRIORITY, CTcuNode

    def open_node(*args, **kwargs):
        return CTcuNode.open(*args, priority=DEFAULT_PRIORITY if priority is None else priority, **kwargs)

    return open_node


def run(args, out=None, err=None, prog="dct-hil tcu"):
    """Runs the node ``--impl`` names (``tcu_stub.can_tcu.run``)."""
    open_node = _c_opener(getattr(args, "priority", None)) if getattr(args, "impl", "c") == "c" else None
    return can_tcu.run(args, out=out, err=err, prog=prog, open_node=open_node)


def main(argv=None):
    parser = can_tcu._Parser(prog="python -m tcu_stub.command",
                             description="The reference TCU as a CAN node against the plant server: "
                                         "2 ms task, E2E-protected frames, safe frames on exit.")
    can_tcu.add_arguments(parser)
    args = parser.parse_args(argv)
    return run(args, prog=parser.prog)


if __name__ == "__main__":
    sys.exit(main())
