//! Certificates and secrets the deployment tests make: a CA of their own, a certificate per
//! server for its name and address, and token secrets unique to the run.

use std::path::Path;

/// A CA and, for each `(host, address, dir)`, a certificate for the host's name and address
/// written to `dir/HOST.crt` and `dir/HOST.key`; returns the CA's PEM.
pub fn pki(servers: &[(&str, String, &Path)]) -> String {
    let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "wavesplat deployment test CA");
    let ca_key = rcgen::KeyPair::generate().unwrap();
    let ca = ca_params.self_signed(&ca_key).unwrap();
    for (host, ip, dir) in servers {
        let params = rcgen::CertificateParams::new(vec![host.to_string(), ip.clone()]).unwrap();
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = params.signed_by(&key, &ca, &ca_key).unwrap();
        std::fs::write(dir.join(format!("{host}.crt")), cert.pem()).unwrap();
        std::fs::write(dir.join(format!("{host}.key")), key.serialize_pem()).unwrap();
    }
    ca.pem()
}

/// A token secret unique to this run.
pub fn secret(what: &str) -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos();
    format!("{what}-{nanos:x}-{:x}", std::process::id())
}
