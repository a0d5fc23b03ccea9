// UTM (WGS84) to latitude and longitude and back: the transverse Mercator projection by
// Krüger's series to sixth order in n, as given by C. F. F. Karney, "Transverse Mercator
// with an accuracy of a few nanometers", J. Geodesy 85 (2011) 475-485,
// doi:10.1007/s00190-011-0445-3 (inverse: eqs. 7, 11-21, 26-27, 36; forward: eqs. 7-12,
// 35). Within the UTM zones its error is far below a millimetre.
"use strict";

const seamapUtm = (() => {
  const a = 6378137.0; // WGS84 semi-major axis, metres
  const f = 1 / 298.257223563; // WGS84 flattening
  const k0 = 0.9996; // UTM scale on the central meridian
  const falseEasting = 500000.0;
  const southFalseNorthing = 10000000.0;

  const e = Math.sqrt(f * (2 - f)); // first eccentricity
  const n = f / (2 - f); // third flattening
  const n2 = n * n, n3 = n2 * n, n4 = n3 * n, n5 = n4 * n, n6 = n5 * n;
  // Rectifying radius A (eq. 14).
  const A = (a / (1 + n)) * (1 + n2 / 4 + n4 / 64 + n6 / 256);
  // Karney's alpha_j (eq. 35), index j-1: the forward series.
  const alpha = [
    n / 2 - (2 / 3) * n2 + (5 / 16) * n3 + (41 / 180) * n4 - (127 / 288) * n5 +
      (7891 / 37800) * n6,
    (13 / 48) * n2 - (3 / 5) * n3 + (557 / 1440) * n4 + (281 / 630) * n5 -
      (1983433 / 1935360) * n6,
    (61 / 240) * n3 - (103 / 140) * n4 + (15061 / 26880) * n5 + (167603 / 181440) * n6,
    (49561 / 161280) * n4 - (179 / 168) * n5 + (6601661 / 7257600) * n6,
    (34729 / 80640) * n5 - (3418889 / 1995840) * n6,
    (212378941 / 319334400) * n6,
  ];
  // Karney's beta_j (eq. 36), index j-1: the inverse series.
  const beta = [
    n / 2 - (2 / 3) * n2 + (37 / 96) * n3 - (1 / 360) * n4 - (81 / 512) * n5 +
      (96199 / 604800) * n6,
    (1 / 48) * n2 + (1 / 15) * n3 - (437 / 1440) * n4 + (46 / 105) * n5 -
      (1118711 / 3870720) * n6,
    (17 / 480) * n3 - (37 / 840) * n4 - (209 / 4480) * n5 + (5569 / 90720) * n6,
    (4397 / 161280) * n4 - (11 / 504) * n5 - (830251 / 7257600) * n6,
    (4583 / 161280) * n5 - (108847 / 3991680) * n6,
    (20648693 / 638668800) * n6,
  ];

  // tau = tan(phi) from tau' = tan(conformal latitude) by Newton's method (eqs. 19-21).
  function tauFromTauPrime(tauPrime) {
    let tau = tauPrime;
    for (let i = 0; i < 10; i++) {
      const sigma = Math.sinh(e * Math.atanh((e * tau) / Math.hypot(1, tau)));
      const tauI = tau * Math.hypot(1, sigma) - sigma * Math.hypot(1, tau);
      const step =
        ((tauPrime - tauI) / Math.hypot(1, tauI)) *
        ((1 + (1 - e * e) * tau * tau) / ((1 - e * e) * Math.hypot(1, tau)));
      tau += step;
      if (Math.abs(step) < 1e-14) break;
    }
    return tau;
  }

  // Latitude and longitude (degrees, WGS84) and the meridian convergence (degrees: the
  // angle from true north to grid north, clockwise) of a UTM point (metres) in `zone`
  // (1..60), southern hemisphere when `south`.
  function toLatLon(east, north, zone, south) {
    const x = east - falseEasting;
    const y = south ? north - southFalseNorthing : north;
    const xi = y / (k0 * A);
    const eta = x / (k0 * A);
    let xiP = xi, etaP = eta, p = 1, q = 0;
    for (let j = 1; j <= 6; j++) {
      const b = beta[j - 1];
      const s2 = Math.sin(2 * j * xi), c2 = Math.cos(2 * j * xi);
      const sh = Math.sinh(2 * j * eta), ch = Math.cosh(2 * j * eta);
      xiP -= b * s2 * ch; // eq. 11
      etaP -= b * c2 * sh;
      p -= 2 * j * b * c2 * ch; // eq. 26 (inverse)
      q += 2 * j * b * s2 * sh;
    }
    const sinhEtaP = Math.sinh(etaP);
    const sinXiP = Math.sin(xiP), cosXiP = Math.cos(xiP);
    const tauPrime = sinXiP / Math.hypot(sinhEtaP, cosXiP); // eq. 18
    const tau = tauFromTauPrime(tauPrime);
    const lat = Math.atan(tau);
    const lon0 = ((zone - 1) * 6 - 180 + 3) * (Math.PI / 180);
    const lon = lon0 + Math.atan2(sinhEtaP, cosXiP); // eq. 18
    // Convergence (eq. 27 with the inverse series' p, q).
    const gamma = Math.atan(Math.tan(xiP) * Math.tanh(etaP)) + Math.atan2(q, p);
    const deg = 180 / Math.PI;
    return { lat: lat * deg, lon: lon * deg, convergenceDeg: gamma * deg };
  }

  // UTM easting and northing (metres) in `zone` (1..60), southern hemisphere when `south`,
  // of a point at latitude and longitude (degrees, WGS84); the zone need not be the
  // point's own (a gap straddling a zone edge stays on the survey's grid).
  function fromLatLon(lat, lon, zone, south) {
    const rad = Math.PI / 180;
    const lon0 = ((zone - 1) * 6 - 180 + 3) * rad;
    let lambda = lon * rad - lon0;
    lambda = Math.atan2(Math.sin(lambda), Math.cos(lambda)); // into (-pi, pi]
    const tau = Math.tan(lat * rad);
    const sigma = Math.sinh(e * Math.atanh((e * tau) / Math.hypot(1, tau))); // eq. 9
    const tauP = tau * Math.hypot(1, sigma) - sigma * Math.hypot(1, tau); // eq. 7
    const cosL = Math.cos(lambda);
    const xiP = Math.atan2(tauP, cosL); // eq. 10
    const etaP = Math.asinh(Math.sin(lambda) / Math.hypot(tauP, cosL));
    let xi = xiP, eta = etaP;
    for (let j = 1; j <= 6; j++) { // eq. 11
      const a2 = alpha[j - 1];
      xi += a2 * Math.sin(2 * j * xiP) * Math.cosh(2 * j * etaP);
      eta += a2 * Math.cos(2 * j * xiP) * Math.sinh(2 * j * etaP);
    }
    return {
      e: falseEasting + k0 * A * eta,
      n: (south ? southFalseNorthing : 0) + k0 * A * xi,
    };
  }

  // The zone and hemisphere of a WGS84 UTM EPSG code (326zz north, 327zz south); null
  // for any other code.
  function zoneOf(epsg) {
    if (epsg >= 32601 && epsg <= 32660) return { zone: epsg - 32600, south: false };
    if (epsg >= 32701 && epsg <= 32760) return { zone: epsg - 32700, south: true };
    return null;
  }

  return { toLatLon, fromLatLon, zoneOf };
})();
