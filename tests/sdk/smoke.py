"""The service through a Python SDK generated from openapi/openapi.json (openapi-python-client).

    python tests/sdk/smoke.py BASE_URL BUNDLE.tar
"""

import sys
import time

import httpx
from crestscan_client import Client
from crestscan_client.api.cmm import get_cmm_comparison, put_cmm
from crestscan_client.api.connections import get_connection
from crestscan_client.api.inspections import create_inspection, get_inspection, inspection_events, list_inspections
from crestscan_client.api.results import get_report, get_threads
from crestscan_client.models import CmmMeasurements, CmmPoint, Inspection, Problem, ThreadTable
from crestscan_client.types import File


def main(base: str, bundle: str) -> None:
    client = Client(base_url=base, timeout=httpx.Timeout(120.0), raise_on_unexpected_status=True)
    with open(bundle, "rb") as f:
        created = create_inspection.sync(
            client=client,
            body=File(payload=f, file_name="bundle.tar", mime_type="application/octet-stream"),
            client_reference="sdk-smoke",
            idempotency_key="sdk-smoke-1",
        )
    assert isinstance(created, Inspection), created
    print(f"sdk: submitted {created.id}")

    deadline = time.monotonic() + 300
    while True:
        inspection = get_inspection.sync(client=client, id=created.id)
        assert isinstance(inspection, Inspection), inspection
        if inspection.status.value in ("succeeded", "failed", "canceled"):
            break
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.5)
    assert inspection.status.value == "succeeded", inspection.error
    assert inspection.verdict in ("accept", "reject")
    # The event stream of a finished inspection: its one state, then the end of the stream.
    events = inspection_events.sync(client=client, id=created.id)
    assert isinstance(events, str) and events.count("event: state") == 1, events
    assert '"status":"succeeded"' in events, events

    report = get_report.sync_detailed(client=client, id=created.id)
    assert report.status_code == 200
    assert report.headers["etag"].startswith('"')

    table = get_threads.sync(client=client, id=created.id)
    assert isinstance(table, ThreadTable), table
    measured = [(t.thread, h.angle_deg, h.height_mm) for t in table.threads for h in t.heights if isinstance(h.height_mm, float)]
    assert measured, "no measured bins"

    points = [CmmPoint(thread=t, angle_deg=a, height_mm=h - 0.002) for t, a, h in measured]
    stored = put_cmm.sync(client=client, id=created.id, body=CmmMeasurements(points=points, instrument="sdk smoke"))
    assert not isinstance(stored, Problem), stored
    comparison = get_cmm_comparison.sync(client=client, id=created.id)
    assert not isinstance(comparison, Problem), comparison
    agreement = comparison.agreement
    assert agreement.compared == len(points), agreement
    assert abs(agreement.bias_mm - 0.002) < 1e-5, agreement.bias_mm

    page = list_inspections.sync(client=client, client_reference="sdk-smoke")
    assert [i.id for i in page.items] == [created.id], page

    missing = get_inspection.sync(client=client, id="not-an-id")
    assert isinstance(missing, Problem) and missing.code == "invalid_id", missing
    connection = get_connection.sync_detailed(client=client, designation="BC 4-1/2")
    assert connection.status_code == 200, connection.content
    print(f"sdk: OK (verdict {inspection.verdict}, {len(points)} CMM points, bias {agreement.bias_mm * 1000:.3f} µm)")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
