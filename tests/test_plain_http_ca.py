"""A plain-http Prefect API spares each Prefect client the parse of the whole CA bundle
(capvector.flows.runtime.prefect_server._no_ca_bundle_for_plain_http); an https one keeps Prefect's
verification, and a certificate file the user named is kept."""

import ssl

from capvector.flows.runtime import prefect_server


def test_plain_http_gets_a_one_certificate_bundle_that_parses(tmp_path, monkeypatch):
    monkeypatch.setenv("PREFECT_HOME", str(tmp_path / "prefect"))
    monkeypatch.setenv("PREFECT_API_URL", "http://127.0.0.1:4200/api")
    monkeypatch.delenv("PREFECT_API_SSL_CERT_FILE", raising=False)
    prefect_server._no_ca_bundle_for_plain_http()
    bundle = tmp_path / "prefect" / prefect_server.PLAIN_HTTP_CA
    assert prefect_server.os.environ["PREFECT_API_SSL_CERT_FILE"] == str(bundle)
    assert bundle.read_text().count("BEGIN CERTIFICATE") == 1
    context = ssl.create_default_context(cafile=str(bundle))  # what Prefect does with it
    assert len(context.get_ca_certs()) == 1


def test_https_and_a_users_certificate_file_are_left_alone(tmp_path, monkeypatch):
    monkeypatch.setenv("PREFECT_HOME", str(tmp_path / "prefect"))
    monkeypatch.setenv("PREFECT_API_URL", "https://prefect.example.org/api")
    monkeypatch.delenv("PREFECT_API_SSL_CERT_FILE", raising=False)
    prefect_server._no_ca_bundle_for_plain_http()
    assert "PREFECT_API_SSL_CERT_FILE" not in prefect_server.os.environ
    monkeypatch.setenv("PREFECT_API_URL", "http://127.0.0.1:4200/api")
    monkeypatch.setenv("PREFECT_API_SSL_CERT_FILE", "/etc/my-ca.pem")
    prefect_server._no_ca_bundle_for_plain_http()
    assert prefect_server.os.environ["PREFECT_API_SSL_CERT_FILE"] == "/etc/my-ca.pem"
    assert not (tmp_path / "prefect").exists()
