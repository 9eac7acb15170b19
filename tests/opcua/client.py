#!/usr/bin/env python3
"""A real OPC UA client (asyncua, PyPI) for crestscan's OPC UA server; the Rust tests drive it.

    client.py probe URL [--key KEY]   connect, browse the VisionSystem, read its state and recipe
    client.py watch URL [--key KEY]   the same, then subscribe to ResultReady events and print the
                                      first one (after a line {"subscribed": true}), then call
                                      GetResultById for it and for an unknown id, and
                                      GetResultListFiltered by its JobId and unfiltered

--secure DIR signs and encrypts the channel (Basic256Sha256) with a client certificate kept in DIR
(made there the first time: DIR/client-cert.der, DIR/client-key.pem).

One JSON object per line on stdout. A refused connection prints {"refused": ...} and exits 3; no
event within --timeout seconds exits 4.
"""
import argparse
import asyncio
import dataclasses
import json
import pathlib
import socket
import sys

from asyncua import Client, ua

NAMESPACE = "urn:crestscan:machine-vision"
MACHINE_VISION = "http://opcfoundation.org/UA/MachineVision"


def emit(obj):
    print(json.dumps(obj), flush=True)


def plain(value):
    if isinstance(value, ua.LocalizedText):
        return value.Text
    if isinstance(value, list):
        return [plain(v) for v in value]
    if isinstance(value, float) and value != value:
        return None
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, bytes):
        return value.hex()
    if dataclasses.is_dataclass(value):
        # A structure decoded with the definitions the server published.
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, ua.ExtensionObject):
        return {"undecoded": value.TypeId.to_string()}
    return str(value)


async def secure(client, folder):
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
    from cryptography.x509.oid import ExtendedKeyUsageOID

    client.application_uri = "urn:crestscan:opcua-test-client"
    key, cert = folder / "client-key.pem", folder / "client-cert.der"
    await setup_self_signed_certificate(
        key,
        cert,
        client.application_uri,
        socket.gethostname(),
        [ExtendedKeyUsageOID.CLIENT_AUTH],
        {"commonName": "crestscan opcua test client"},
    )
    await client.set_security(
        SecurityPolicyBasic256Sha256, cert, key, mode=ua.MessageSecurityMode.SignAndEncrypt
    )


class Handler:
    def __init__(self):
        self.events = asyncio.Queue()

    def event_notification(self, event):
        fields = event.get_event_props_as_fields_dict()
        self.events.put_nowait({name: plain(variant.Value) for name, variant in fields.items()})


async def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=["probe", "watch"])
    parser.add_argument("url")
    parser.add_argument("--key")
    parser.add_argument("--timeout", type=float, default=180)
    parser.add_argument("--secure")
    args = parser.parse_args()

    client = Client(url=args.url, timeout=10)
    if args.key:
        client.set_user("mes")
        client.set_password(args.key)
    try:
        if args.secure:
            await secure(client, pathlib.Path(args.secure))
        await client.connect()
    except Exception as e:  # the refusal is the answer the test reads
        emit({"refused": type(e).__name__, "detail": str(e)})
        return 3
    try:
        ns = await client.get_namespace_index(NAMESPACE)
        mv = await client.get_namespace_index(MACHINE_VISION)
        # The structures of OPC 40100-1 (ResultIdDataType, …) as the server defines them. asyncua
        # knows "TrimmedString" by name as the core's (1.05), so it skips OPC 40100-1's own (a 1.04
        # model, i=3017 in its namespace): that one is a String too.
        ua.basetype_by_datatype[ua.NodeId(3017, mv)] = "String"
        await client.load_data_type_definitions()
        system = await client.nodes.objects.get_child([f"{ns}:VisionSystem"])
        system_type = client.get_node(await system.read_type_definition())
        children = sorted([(await c.read_browse_name()).to_string() for c in await system.get_children()])
        machine = await system.get_child([f"{mv}:VisionStateMachine"])
        state = await machine.get_child(["0:CurrentState"])
        state_node = client.get_node(await (await state.get_child(["0:Id"])).read_value())
        state_number = await state_node.get_child(["0:StateNumber"])
        execution = await machine.get_child([f"{ns}:ExecutionState"])
        recipe = await system.get_child(
            [f"{mv}:RecipeManagement", f"{mv}:Recipes", f"{ns}:default", f"{ns}:Content"]
        )
        configurations = await system.get_child([f"{mv}:ConfigurationManagement", f"{mv}:Configurations"])
        stations = {}
        for station in await configurations.get_children():
            name = (await station.read_browse_name()).Name
            status = await station.get_child([f"{ns}:Status"])
            stations[name] = await status.read_value()
        emit(
            {
                "namespaces": {"crestscan": ns, "machine_vision": mv},
                "type": (await system_type.read_browse_name()).to_string(),
                "children": children,
                "state": plain(await state.read_value()),
                "state_node": (await state_node.read_browse_name()).to_string(),
                "state_number": await state_number.read_value(),
                "machine_type": (await client.get_node(await machine.read_type_definition()).read_browse_name()).to_string(),
                "execution": plain(await execution.read_value()),
                "recipe": json.loads(await recipe.read_value()),
                "stations": stations,
                "security_policy": client.security_policy.URI,
            }
        )
        if args.mode == "probe":
            return 0
        handler = Handler()
        subscription = await client.create_subscription(100, handler)
        # crestscan's subtype of OPC 40100-1's ResultReadyEventType: its fields and the supertype's.
        event_type = client.get_node(ua.NodeId("ThreadResultReadyEventType", ns))
        # No where clause: async-opcua 0.16 compares only numbers and booleans in InList, so the
        # EventType InList asyncua generates matches no event (docs/interchange.md, "OPC UA").
        # Only ResultReady events have the VisionSystem as their notifier.
        await subscription.subscribe_events(system, event_type, where_clause_generation=False)
        emit({"subscribed": True})
        try:
            event = await asyncio.wait_for(handler.events.get(), args.timeout)
        except asyncio.TimeoutError:
            emit({"timeout": args.timeout})
            return 4
        emit({"event": event})
        # ResultManagementType's GetResultById, for the announced result and for an unknown one.
        results = await system.get_child([f"{mv}:ResultManagement"])
        method = await results.get_child([f"{mv}:GetResultById"])
        for result_id in [event["ResultId"]["Id"], "no-such-result"]:
            handle, result, error = await results.call_method(
                method, ua.ResultIdDataType(Id=result_id), ua.Variant(0, ua.VariantType.Int32)
            )
            emit({"get_result_by_id": result_id, "handle": handle, "result": plain(result), "error": error})
        # GetResultListFiltered: by the event's JobId, then every result (no filter, no limit).
        method = await results.get_child([f"{mv}:GetResultListFiltered"])
        for job in [event["JobId"]["Id"], ""]:
            nulls = [ua.Variant(None, ua.VariantType.ExtensionObject) for _ in range(7)]
            complete, count, handle, listed, error = await results.call_method(
                method,
                ua.Variant(0, ua.VariantType.Int32),
                *nulls,
                ua.JobIdDataType(Id=job),
                ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(-1, ua.VariantType.Int32),
            )
            emit(
                {
                    "get_result_list_filtered": job,
                    "complete": complete,
                    "count": count,
                    "ids": [r.ResultId.Id for r in listed or []],
                    "error": error,
                }
            )
        return 0
    finally:
        await client.disconnect()


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
