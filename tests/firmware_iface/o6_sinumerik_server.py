"""The documented SINUMERIK nodes served by open62541 (PyPI's ``o6``) in a process of its own.

A cross-check of the OPC UA client with a stack other than asyncua's. ``o6``'s
free build ends its process ten minutes after the import, so it never runs in
the test process: ``python o6_sinumerik_server.py PORT`` prints ``READY`` when
the server listens and serves until its standard input closes.
"""

from __future__ import annotations

import sys

import o6

# registers the namespace on this module (o6 publishes a module's namespaces)
o6.ns.namespace("sinumerik", uri="SinumerikVarProvider", version="1.0")

NODES = {
    "/Channel/MachineAxis/actToolBasePos[u1,1]": (1250.5, o6.Double),
    "/Channel/MachineAxis/actToolBasePos[u1,2]": (-300.25, o6.Double),
    "/Channel/MachineAxis/actToolBasePos[u1,3]": (-42.0, o6.Double),
    "/Channel/State/progStatus[u1]": (3, o6.UInt16),
    "/Channel/State/chanStatus[u1]": (1, o6.UInt16),
    "/Channel/ProgramInfo/selectedWorkPProg[u1]": ("/_N_MPF_DIR/_N_XMALIGN_MPF", o6.String),
    "/Bag/State/opMode[u1]": (2, o6.UInt16),
}


def main(port: int) -> None:
    server = o6.Server(port=port)
    server.ns.append(sys.modules[__name__])
    server.start()
    for node_id, (value, data_type) in NODES.items():
        server.addVariable(
            node_id,
            server.objectsNode,
            data_type(value),
            nodeId=o6.NodeId(f"ns=2;s={node_id}"),
            ns=2,
        )
    print("READY", flush=True)
    sys.stdin.read()
    server.stop()


if __name__ == "__main__":
    main(int(sys.argv[1]))
