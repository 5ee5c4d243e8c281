"""A broker reachable from other machines speaks TLS, or the operator says in so many words that
the network is already encrypted: ``cblrs broker-config`` refuses a listener beyond loopback
without TLS (passwords and detections would cross the network in clear), and a NATS cluster
beyond loopback without TLS at all (its routes would authenticate nothing)."""

from __future__ import annotations

import pytest
from broker_user import RUN_AS

from cblrs.cli.main import main
from cblrs.runtime.addresses import is_loopback_host

AS = ["--run-as", RUN_AS] if RUN_AS else []


def test_loopback_names_and_addresses():
    assert all(is_loopback_host(host) for host in ("127.0.0.1", "::1", "localhost", "127.0.0.2"))
    assert not any(is_loopback_host(host) for host in ("0.0.0.0", "::", "10.0.0.1",
                                                       "no-such-host.invalid"))


@pytest.mark.parametrize("arguments", [
    ["--bind", "0.0.0.0"],
    ["--bind", "10.1.2.3"],
    ["--backbone", "nats", "--no-tls", "--nodes", "10.1.2.3"],
])
def test_a_listener_beyond_loopback_without_tls_is_refused(tmp_path, capsys, arguments):
    out = tmp_path / "broker"
    assert main(["broker-config", "--out", str(out), "--cameras", "CVLab1", *arguments]) == 1
    error = capsys.readouterr().err
    assert "in clear" in error and "--allow-plaintext" in error and "Traceback" not in error
    assert not any(out.rglob("*.conf"))  # nothing written


def test_a_nats_cluster_beyond_loopback_without_tls_is_refused_even_when_plaintext_is_allowed(
        tmp_path, capsys):
    out = tmp_path / "nats"
    code = main(["broker-config", "--backbone", "nats", "--out", str(out), "--cameras", "CVLab1",
                 "--no-tls", "--allow-plaintext", "--nodes", "10.1.2.3,10.1.2.4,10.1.2.5"])
    error = capsys.readouterr().err
    assert code == 1 and "routes" in error and "Traceback" not in error
    assert not any(out.rglob("*.conf"))


def test_plaintext_beyond_loopback_when_the_operator_says_so(tmp_path):
    out = tmp_path / "broker"
    assert main(["broker-config", "--out", str(out), "--cameras", "CVLab1", "--bind", "0.0.0.0",
                 "--allow-plaintext", "--json", *AS]) == 0
    assert "listener 1883 0.0.0.0" in (out / "mosquitto.conf").read_text()


@pytest.mark.parametrize("arguments", [
    ["--bind", "0.0.0.0", "--tls"],
    ["--bind", "127.0.0.1"],
    ["--backbone", "nats", "--nodes", "10.1.2.3,10.1.2.4,10.1.2.5"],
    ["--backbone", "nats", "--no-tls"],
])
def test_tls_or_loopback_needs_no_permission(tmp_path, arguments):
    out = tmp_path / "broker"
    mosquitto = [] if "nats" in arguments else AS
    assert main(["broker-config", "--out", str(out), "--cameras", "CVLab1", *arguments,
                 "--json", *mosquitto]) == 0
