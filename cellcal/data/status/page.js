// The cellcal status page: one EventSource on the service's event stream, nothing else.
// Read-only: each state shows the command that acts on it. Plain JavaScript, no library,
// nothing loaded from outside (cell PCs are offline).
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const SVG = "http://www.w3.org/2000/svg"; // a namespace name, never fetched
  const MAX_POSES = 30;
  const MAX_EVENTS = 40;
  const COLORS = ["#0969da", "#bf3989", "#1a7f37", "#9a6700", "#8250df"];
  const ACTIVE = ["running", "pausing", "aborting", "analysing"];

  // One campaign is shown: the service's (the running one, else the one held, else the
  // last one). Every pose listed and plotted, and the end shown, are that campaign's.
  let snap = null; // the last status
  let poses = []; // the campaign's last stored poses, oldest first
  let end = null; // the last campaign-end
  let live = false;
  let etaAt = null; // wall time (ms) the campaign should end

  const fix = (x, d) => (x === null || x === undefined || Number.isNaN(x) ? "—" : Number(x).toFixed(d));
  const vec = (v, d, scale = 1) => (v ? v.map((x) => fix(x * scale, d)).join(", ") : "—");
  const norm = (v) => Math.sqrt(v.reduce((a, x) => a + x * x, 0));
  const clock = (ms) => new Date(ms).toLocaleTimeString();
  const shownId = () => (snap && snap.campaign ? snap.campaign.id : null);
  const HELD = ["paused", "interrupted"];

  function el(tag, text, cls) {
    const e = document.createElement(tag);
    if (text !== undefined) e.textContent = text;
    if (cls) e.className = cls;
    return e;
  }

  function row(cells, first = "td") {
    const tr = el("tr");
    cells.forEach((c, i) => tr.append(el(i === 0 ? first : "td", c)));
    return tr;
  }

  function duration(s) {
    if (s < 90) return `${Math.round(s)} s`;
    if (s < 5400) return `${Math.round(s / 60)} min`;
    return `${(s / 3600).toFixed(1)} h`;
  }

  function notReady(s) {
    return Object.values(s.devices || {}).some((d) => d.state !== "ready");
  }

  function commandFor(s) {
    const c = s.campaign;
    const id = s.paused_campaign ?? (c ? c.id : "ID");
    switch (s.state) {
      case "idle":
        return notReady(s)
          ? "journalctl -u cellcal -e   (why a device is not ready)"
          : "cellcal campaign start --config FILE";
      case "running":
        return "cellcal campaign pause   |   cellcal campaign pause --now   |   cellcal campaign abort";
      case "pausing":
        return "cellcal campaign pause --now   |   cellcal campaign abort";
      case "paused":
        return `cellcal campaign resume ${id}   |   cellcal campaign abort ${id}`;
      case "aborting":
        return "nothing: the robot is being stopped, every stored pose is kept";
      case "analysing":
        return "nothing: cellcal campaign watch shows the result";
      case "stopping":
        return "systemctl start cellcal   (once it has stopped)";
      default:
        return "systemctl status cellcal";
    }
  }

  function setLive(up) {
    live = up;
    const link = $("link");
    link.className = `link ${up ? "up" : "down"}`;
    link.textContent = up ? "live" : `unreachable since ${clock(Date.now())}`;
    if (!up) {
      $("state").className = "state unreachable";
      $("command").textContent = "systemctl status cellcal";
    } else if (snap) {
      renderState();
    }
  }

  function renderState() {
    const s = snap;
    $("state").textContent = s.state;
    $("state").className = `state ${s.state}`;
    $("reason").textContent = s.reason;
    $("command").textContent = commandFor(s);
    const items = Object.entries(s.devices || {}).map(([name, d]) => {
      const li = el("li");
      li.append(el("span", d.state, `dev ${d.state}`), `${name}${d.message ? ` — ${d.message}` : ""}`);
      return li;
    });
    $("devices").replaceChildren(...items);
  }

  // The headings name the campaign shown.
  function renderTitles() {
    const id = shownId();
    const of = id === null ? "no campaign yet" : `campaign ${id}`;
    $("plot-title").textContent = `σ and time per pose, ${of}`;
    $("poses-title").textContent = `Last poses of ${of}`;
    const last = poses[poses.length - 1];
    $("sensors-title").textContent = last
      ? `Sensors at the last stored pose, campaign ${id}, pose ${last.idx}`
      : `Sensors at the last stored pose, ${of}`;
  }

  // A campaign held (paused, or interrupted by a stop or a restart): what to do.
  function heldNote(c) {
    if (!HELD.includes(c.status) || ACTIVE.includes(snap.state)) return "";
    const left = (c.planned || 0) - (c.stored || 0);
    const why = c.status === "interrupted" ? "interrupted" : "paused";
    return (
      `${why} with ${c.stored} of ${c.planned} poses stored (kept): ` +
      `cellcal campaign resume ${c.id} measures the ${left} left, each once; ` +
      `or cellcal campaign abort ${c.id}`
    );
  }

  function renderCampaign() {
    renderTitles();
    const c = snap && snap.campaign;
    if (!c) return;
    $("campaign-id").textContent = c.id;
    $("campaign-kind").textContent = c.kind || ""; // calibration, iso9283 (from the service)
    $("campaign-status").textContent = c.status || "";
    $("campaign-status").className = `cstatus ${c.status || ""}`;
    const planned = c.planned || 0;
    const stored = c.stored || 0;
    $("bar").style.width = planned ? `${(100 * stored) / planned}%` : "0";
    $("progress").textContent = planned ? `pose ${stored} of ${planned}` : "starting";
    const note = heldNote(c);
    $("held").textContent = note;
    $("held").hidden = !note;
    $("roles").textContent = Object.entries(c.roles || {})
      .map(([role, r]) => `${role} ${r.stored}${r.planned === undefined ? " stored" : ` of ${r.planned}`}`)
      .join("  ·  ");
    etaAt = c.eta_s !== null && c.eta_s !== undefined ? Date.now() + 1000 * c.eta_s : etaAt;
    const body = [
      row([`pose ${c.pose_idx ?? "—"}`, `${c.role || ""} ${c.region || ""}`], "th"),
      row(["target (mm)", vec(c.target_mm, 3)], "th"),
      row(["planned (°)", vec(c.planned_q_deg, 3)], "th"),
      row([`reached (°), pose ${c.reached_idx ?? "—"}`, vec(c.reached_q_deg, 3)], "th"),
    ];
    $("pose").tBodies[0].replaceChildren(...body);
  }

  // Once a second and on every status: the phase with the dwell's countdown, the ETA.
  function tick() {
    const c = snap && snap.campaign;
    if (!c) return;
    const active = ACTIVE.includes(snap.state);
    let phase = `${c.phase || ""}`;
    if (active && c.pose_idx !== undefined && c.phase !== "starting") {
      const names = { move: "moving", dwell: "dwell", sample: "sampling" };
      phase = `pose ${c.pose_idx}: ${names[c.phase] || c.phase}`;
      if (c.phase === "dwell" && c.dwell_wall_s > 0 && c.phase_started) {
        const left = Math.max(0, c.dwell_wall_s - (Date.now() / 1000 - c.phase_started));
        phase += `, ${left.toFixed(1)} s of ${fix(c.dwell_wall_s, 1)} s left`;
      }
    }
    if (snap.state === "analysing") phase = "analysing: registration, calibration, validation";
    $("phase").textContent = `phase: ${phase}`;
    $("eta").textContent =
      active && etaAt && snap.state !== "analysing"
        ? `ETA ${clock(etaAt)} (about ${duration(Math.max(0, (etaAt - Date.now()) / 1000))} left)`
        : "";
  }

  // The service's σ (sigma_mm: the 3-D norm of the per-axis standard deviations), in µm.
  function sigma(p, sensor) {
    const s = p.sensors[sensor];
    if (!s) return null;
    if (s.sigma_mm !== undefined) return s.sigma_mm === null ? null : 1000 * s.sigma_mm;
    return s.std_mm ? 1000 * norm(s.std_mm) : null;
  }

  function sensorNames() {
    return [...new Set(poses.flatMap((p) => Object.keys(p.sensors || {})))];
  }

  function renderPoses() {
    const names = sensorNames();
    $("poses-sigma").textContent = `3-D σ (µm): ${names.join(" / ") || "—"}`;
    const rows = poses
      .slice()
      .reverse()
      .map((p) => {
        const tr = row([
          `${p.idx}`,
          p.role,
          p.region,
          vec(p.target_mm, 1),
          fix(p.seconds, 2),
          `${p.retries}`,
          names.map((n) => fix(sigma(p, n), 1)).join(" / "),
        ]);
        tr.dataset.campaign = p.campaign_id; // whose pose it is
        return tr;
      });
    $("poses").tBodies[0].replaceChildren(...rows);
    const last = poses[poses.length - 1];
    const sensors = last
      ? Object.entries(last.sensors).map(([n, s]) =>
          row([n, `${s.n}`, vec(s.mean_mm, 3), vec(s.std_mm, 1, 1000)]),
        )
      : [];
    $("sensors").tBodies[0].replaceChildren(...sensors);
    renderTitles();
    plot();
  }

  function niceMax(v) {
    if (!(v > 0)) return 1;
    const p = 10 ** Math.floor(Math.log10(v));
    return [1, 2, 5, 10].map((m) => m * p).find((m) => m >= v);
  }

  function svg(tag, attrs, text) {
    const e = document.createElementNS(SVG, tag);
    Object.entries(attrs).forEach(([k, v]) => e.setAttribute(k, v));
    if (text !== undefined) e.textContent = text;
    return e;
  }

  // The key: a line per sensor's σ, the bars of the time, each with its unit.
  function legend(names) {
    const g = svg("g", { class: "legend" });
    let x = 70;
    names.forEach((name, k) => {
      const color = COLORS[k % COLORS.length];
      g.append(svg("line", { x1: x, x2: x + 24, y1: 11, y2: 11, stroke: color, "stroke-width": 2 }));
      g.append(svg("circle", { cx: x + 12, cy: 11, r: 3, fill: color }));
      const label = `${name}: 3-D σ (µm)`;
      g.append(svg("text", { x: x + 30, y: 15 }, label));
      x += 40 + 7 * label.length;
    });
    g.append(svg("rect", { x, y: 5, width: 12, height: 12, fill: "#8c959f" }));
    g.append(svg("text", { x: x + 18, y: 15 }, "time per pose (s)"));
    return g;
  }

  // Two panels over the last poses: each sensor's σ (norm of its x, y, z σ), the seconds.
  function plot() {
    const out = $("plot");
    const W = 900, L = 70, R = 130, PAD = 14, TOP = 24;
    const parts = [];
    if (!poses.length) {
      out.replaceChildren(svg("text", { x: L, y: 60 }, "no pose stored yet"));
      return;
    }
    const n = poses.length;
    const span = W - L - R - 2 * PAD;
    const x = (i) => L + PAD + (n === 1 ? span / 2 : (i * span) / (n - 1));
    const panel = (top, bottom, label, max, unit) => {
      parts.push(svg("line", { x1: L, x2: W - R, y1: bottom, y2: bottom, class: "axis" }));
      parts.push(svg("line", { x1: L, x2: L, y1: top, y2: bottom, class: "axis" }));
      parts.push(svg("text", { x: 4, y: top + 10 }, label));
      parts.push(svg("text", { x: L - 6, y: top + 10, "text-anchor": "end" }, `${max}`));
      parts.push(svg("text", { x: L - 6, y: bottom, "text-anchor": "end" }, "0"));
      parts.push(svg("text", { x: 4, y: top + 26 }, unit));
      return (v) => bottom - ((bottom - top) * v) / max;
    };
    const names = sensorNames();
    const sig = poses.map((p) => names.map((s) => sigma(p, s)));
    const smax = niceMax(Math.max(0, ...sig.flat().filter((v) => v !== null)));
    parts.push(legend(names));
    const ys = panel(TOP + 10, TOP + 140, "σ", smax, "µm");
    names.forEach((name, k) => {
      const color = COLORS[k % COLORS.length];
      const pts = sig.map((v, i) => (v[k] === null ? null : `${x(i)},${ys(v[k])}`)).filter(Boolean);
      parts.push(svg("polyline", { points: pts.join(" "), fill: "none", stroke: color, "stroke-width": 2 }));
      sig.forEach((v, i) => {
        if (v[k] !== null) parts.push(svg("circle", { cx: x(i), cy: ys(v[k]), r: 3, fill: color }));
      });
    });
    const tmax = niceMax(Math.max(0, ...poses.map((p) => p.seconds)));
    const yt = panel(TOP + 170, TOP + 275, "time", tmax, "s");
    const bw = Math.max(2, Math.min(18, (0.7 * (W - L - R)) / n));
    poses.forEach((p, i) => {
      const y = yt(p.seconds);
      parts.push(svg("rect", { x: x(i) - bw / 2, y, width: bw, height: TOP + 275 - y, fill: "#8c959f" }));
    });
    const step = Math.max(1, Math.ceil(n / 15));
    poses.forEach((p, i) => {
      if (i % step === 0 || i === n - 1) {
        parts.push(svg("text", { x: x(i), y: TOP + 292, "text-anchor": "middle" }, `${p.idx}`));
      }
    });
    parts.push(svg("text", { x: W - R + 24, y: TOP + 292 }, "pose"));
    out.replaceChildren(...parts);
  }

  // The result of the campaign shown (another campaign's is not its): its validation
  // errors, or why it was refused; a paused, interrupted or aborted one has none.
  function renderEnd() {
    const ended = end && ["complete", "refused"].includes(end.status);
    $("end-box").hidden = !ended || end.campaign_id !== shownId();
    if ($("end-box").hidden) return;
    $("end-id").textContent = end.campaign_id;
    const v = end.validation_mm;
    const body = v
      ? [
          row(["before calibration", fix(v.before.rms, 4), fix(v.before.max, 4)], "th"),
          row(["after calibration", fix(v.after.rms, 4), fix(v.after.max, 4)], "th"),
        ]
      : [];
    if (body.length) body[1].className = "after";
    $("end").tBodies[0].replaceChildren(...body);
    const msg = $("end-message");
    msg.className = end.status === "complete" ? "" : "refused";
    msg.textContent = v
      ? `${end.status}: RMS ${fix(v.improvement_pct, 1)} % lower after calibration`
      : `${end.status}: ${end.message}`;
  }

  function addEvent(e) {
    const li = el("li", `${clock(Date.now())}  campaign ${e.campaign_id}: ${e.kind} — ${e.message}`);
    const list = $("events");
    list.prepend(li);
    while (list.children.length > MAX_EVENTS) list.lastChild.remove();
  }

  function onStatus(s) {
    const before = shownId();
    snap = s;
    const id = shownId();
    if (s.recent_poses) {
      // The campaign shown and its last poses (a new watcher, a campaign that starts).
      poses = s.recent_poses.filter((p) => p.campaign_id === id).slice(-MAX_POSES);
      renderPoses();
    } else if (id !== before || poses.some((p) => p.campaign_id !== id)) {
      poses = []; // another campaign is shown: none of the last one's poses
      renderPoses();
    }
    if (s.last_end) end = s.last_end;
    renderEnd();
    if (live) renderState();
    renderCampaign();
    tick();
  }

  function connect() {
    const source = new EventSource("v1/events");
    source.onopen = () => setLive(true);
    source.onerror = () => setLive(false); // it reconnects by itself, with Last-Event-ID
    source.addEventListener("status", (e) => onStatus(JSON.parse(e.data)));
    source.addEventListener("pose", (e) => {
      const p = JSON.parse(e.data);
      if (p.campaign_id !== shownId()) return; // only the campaign shown
      poses = poses.filter((q) => q.idx !== p.idx); // once, if a snapshot had it already
      poses.push(p);
      poses = poses.slice(-MAX_POSES);
      renderPoses();
    });
    source.addEventListener("event", (e) => addEvent(JSON.parse(e.data)));
    source.addEventListener("campaign-end", (e) => {
      end = JSON.parse(e.data);
      renderEnd();
    });
  }

  setInterval(tick, 200);
  plot();
  connect();
})();
