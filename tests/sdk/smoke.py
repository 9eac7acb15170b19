"""The service through a Python SDK generated from openapi/openapi.json (openapi-python-client, with
tests/sdk/generator.yaml): every operation the document declares is called at least once, typed,
with `raise_on_unexpected_status=True`, so an answer the document does not declare fails here.

    python tests/sdk/smoke.py BASE_URL BUNDLE.tar
"""

import importlib
import json
import tarfile
import pkgutil
import sys
import time

import httpx
import jsonschema
import crestscan_client.api
from crestscan_client import Client
from crestscan_client.api.admin import create_key, get_audit, list_keys, list_webhook_deliveries, revoke_key
from crestscan_client.api.cmm import get_cmm, get_cmm_comparison, get_training_pairs, list_cmm_versions, put_cmm
from crestscan_client.api.connections import get_connection, list_connections
from crestscan_client.api.inspections import (
    cancel_inspection,
    create_inspection,
    get_inspection,
    inspection_events,
    list_inspections,
)
from crestscan_client.api.operations import get_capabilities, get_manifest_schema, healthz, metrics, readyz
from crestscan_client.api.results import get_image, get_mesh, get_report, get_threads
from crestscan_client.api.stations import (
    create_check,
    create_station,
    create_study,
    get_station,
    get_study,
    list_checks,
    list_stations,
    put_master,
)
from crestscan_client.models import (
    ApiKey,
    ApiKeys,
    AuditPage,
    Capabilities,
    CmmComparison,
    CmmMeasurements,
    CmmPoint,
    CmmVersions,
    CreatedApiKey,
    DeliveryPage,
    Inspection,
    InspectionPage,
    Master,
    NewApiKey,
    ControlChart,
    NewCheck,
    NewStation,
    NewStudy,
    Problem,
    Report,
    Scope,
    StationList,
    StationRecord,
    StoredCmm,
    ThreadTable,
)
from crestscan_client.models.get_mesh_format import GetMeshFormat
from crestscan_client.types import File

called = set()


def call(module, *args, **kwargs):
    """`module.sync_detailed`, recorded; the answer's status and parsed body."""
    called.add(module.__name__.rsplit(".", 1)[-1])
    response = module.sync_detailed(*args, **kwargs)
    return response.status_code, response.parsed


def expect(status_and_parsed, status, kind):
    status_code, parsed = status_and_parsed
    assert status_code == status, (status_code, parsed)
    assert isinstance(parsed, kind), (kind, parsed)
    return parsed


def every_operation():
    names = set()
    for tag in pkgutil.iter_modules(crestscan_client.api.__path__):
        package = importlib.import_module(f"crestscan_client.api.{tag.name}")
        names |= {m.name for m in pkgutil.iter_modules(package.__path__)}
    return names


def main(base: str, bundle: str) -> None:
    client = Client(base_url=base, timeout=httpx.Timeout(120.0), raise_on_unexpected_status=True)
    assert call(healthz, client=client)[0] == 200
    assert call(readyz, client=client)[0] == 200
    status, text = call(metrics, client=client)
    assert status == 200 and "crestscan_build_info" in text, text[:200]
    expect(call(get_capabilities, client=client), 200, Capabilities)
    assert call(list_connections, client=client)[0] == 200
    assert call(get_connection, "BC 4-1/2", client=client)[0] == 200

    with open(bundle, "rb") as f:
        created = expect(call(
            create_inspection,
            client=client,
            body=File(payload=f, file_name="bundle.tar", mime_type="application/octet-stream"),
            client_reference="sdk-smoke",
            idempotency_key="sdk-smoke-1",
        ), 202, Inspection)
    print(f"sdk: submitted {created.id}")
    # A second one, cancelled while queued or running (or found finished: 409, a declared problem).
    with open(bundle, "rb") as f:
        other = expect(call(
            create_inspection, client=client,
            body=File(payload=f, file_name="bundle.tar", mime_type="application/octet-stream"),
            client_reference="sdk-cancel",
        ), 202, Inspection)
    status, _ = call(cancel_inspection, other.id, client=client)
    assert status in (200, 202, 409), status

    # Wait by long-poll, then read the finished inspection's event stream.
    deadline = time.monotonic() + 300
    while True:
        inspection = expect(call(get_inspection, created.id, client=client, wait="30s"), 200, Inspection)
        if inspection.status.value in ("succeeded", "failed", "canceled"):
            break
        assert time.monotonic() < deadline, "timed out"
    assert inspection.status.value == "succeeded", inspection.error
    assert inspection.verdict in ("accept", "reject")
    events = expect(call(inspection_events, created.id, client=client), 200, str)
    assert events.count("event: state") == 1 and '"status":"succeeded"' in events, events

    report = expect(call(get_report, created.id, client=client), 200, Report)
    # Typed: the verdict and decision are enums, the heights parallel their uncertainties.
    assert report.verdict.value == inspection.verdict.value and report.decision.value == inspection.decision.value, report
    assert all(len(t.height_mm.values) == len(t.height_mm.uncertainty_mm) for t in report.threads)
    table = expect(call(get_threads, created.id, client=client), 200, ThreadTable)
    measured = [(t.thread, h.angle_deg, h.height_mm) for t in table.threads for h in t.heights if isinstance(h.height_mm, float)]
    assert measured, "no measured bins"
    mesh = expect(call(get_mesh, created.id, client=client, format_=GetMeshFormat.GLB), 200, File)
    assert mesh.payload.read(4) == b"glTF"
    image = expect(call(get_image, created.id, "height-map", client=client), 200, File)
    assert image.payload.read(8) == b"\x89PNG\r\n\x1a\n"

    points = [CmmPoint(thread=t, angle_deg=a, height_mm=h - 0.002) for t, a, h in measured]
    stored = expect(call(put_cmm, created.id, client=client, body=CmmMeasurements(points=points, instrument="sdk smoke")), 200, StoredCmm)
    assert stored.version == 1, stored
    expect(call(get_cmm, created.id, client=client), 200, StoredCmm)
    versions = expect(call(list_cmm_versions, created.id, client=client), 200, CmmVersions)
    assert [v.version for v in versions.versions] == [1]
    comparison = expect(call(get_cmm_comparison, created.id, client=client), 200, CmmComparison)
    agreement = comparison.agreement
    assert agreement.compared == len(points), agreement
    assert abs(agreement.bias_mm - 0.002) < 1e-5, agreement.bias_mm
    pairs = expect(call(get_training_pairs, created.id, client=client), 200, str)
    assert pairs.count("\n") >= 1, pairs[:200]

    page = expect(call(list_inspections, client=client, client_reference="sdk-smoke"), 200, InspectionPage)
    assert [i.id for i in page.items] == [created.id], page
    missing = expect(call(get_inspection, "00000000-0000-0000-0000-000000000000", client=client), 404, Problem)
    assert missing.code == "invalid_id", missing

    # Keys and the audit (auth is off here: the admin routes answer without a key).
    made = expect(call(create_key, client=client, body=NewApiKey(name="sdk", scopes=[Scope.READ])), 201, CreatedApiKey)
    assert made.token.startswith("csk_")
    keys = expect(call(list_keys, client=client), 200, ApiKeys)
    assert made.key.id in [k.id for k in keys.keys]
    revoked = expect(call(revoke_key, made.key.id, client=client), 200, ApiKey)
    assert revoked.revoked_at is not None
    audit = expect(call(get_audit, client=client, target=str(created.id)), 200, AuditPage)
    assert any(e.action == "PUT /v1/inspections/{id}/cmm" for e in audit.entries), audit
    # No webhook endpoint is configured here: the record is empty, and typed.
    deliveries = expect(call(list_webhook_deliveries, client=client, inspection_id=str(created.id)), 200, DeliveryPage)
    assert deliveries.deliveries == [], deliveries

    # The manifest's published schema, checked by a real JSON Schema validator against the bundle
    # this script submitted, and against a broken copy of it.
    status, schema = call(get_manifest_schema, client=client)
    assert status == 200, status
    schema = schema.to_dict() if hasattr(schema, "to_dict") else schema
    validator = jsonschema.Draft202012Validator(schema)
    validator.check_schema(schema)
    with tarfile.open(bundle) as tar:
        manifest = json.load(tar.extractfile("./manifest.json" if "./manifest.json" in tar.getnames() else "manifest.json"))
    errors = list(validator.iter_errors(manifest))
    assert not errors, [e.message for e in errors]
    broken = dict(manifest, views=[dict(manifest["views"][0], pose={"angle_deg": "north"})])
    del broken["optics"]
    assert len(list(validator.iter_errors(broken))) >= 3, "the schema catches a broken manifest"

    # Stations: one created, a master's certificate stored (twice: 409), a study over a run that
    # is not the master's refused, naming it, and a study that does not exist.
    station = expect(call(create_station, client=client, body=NewStation(name="sdk-line", description="sdk smoke")), 201, StationRecord)
    assert station.status == "unqualified", station
    certified = [CmmPoint(thread=p.thread, angle_deg=p.angle_deg, height_mm=p.height_mm, uncertainty_mm=0.002) for p in points]
    certificate = CmmMeasurements(points=certified, instrument="sdk CMM", measured_at="2026-01-05T08:00:00Z")
    expect(call(put_master, "sdk-line", "M-1", client=client, body=certificate), 201, Master)
    twice = expect(call(put_master, "sdk-line", "M-1", client=client, body=certificate), 409, Problem)
    assert twice.code == "master_exists", twice
    listed = expect(call(list_stations, client=client), 200, StationList)
    assert [s.name for s in listed.items] == ["sdk-line"], listed
    assert [m.serial for m in expect(call(get_station, "sdk-line", client=client), 200, StationRecord).masters] == ["M-1"]
    refused = expect(call(create_study, "sdk-line", client=client, body=NewStudy(inspections=[created.id])), 422, Problem)
    assert refused.code == "study_refused" and refused.culprit == "inspections[0]", refused
    absent = expect(call(get_study, "sdk-line", "nope", client=client), 404, Problem)
    assert absent.code == "not_found", absent
    # Drift control before any study: an empty chart, and a check refused, naming the station.
    chart = expect(call(list_checks, "sdk-line", client=client), 200, ControlChart)
    assert chart.study is None and chart.items == [] and chart.limits == [], chart
    unjudged = expect(call(create_check, "sdk-line", client=client, body=NewCheck(inspection=created.id)), 422, Problem)
    assert unjudged.code == "check_refused" and unjudged.culprit == "station", unjudged

    missed = every_operation() - called
    assert not missed, f"operations the SDK smoke does not call: {sorted(missed)}"
    print(f"sdk: OK, {len(called)} operations (verdict {inspection.verdict}, {len(points)} CMM points, bias {agreement.bias_mm * 1000:.3f} µm)")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
