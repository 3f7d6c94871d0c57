"""The page's own script and style: pointer handling of the viewport, the opacity editor, uploads and
downloads. Served inline by the trame app (no file, no network: the page loads nothing from outside).

Camera events are coalesced in the browser: while one message is on its way to the server, further
pointer motion adds up and goes in the next message, so a slow link or a busy server never builds a
queue of stale camera positions.
"""

VIEWER_SCRIPT = r"""
(function () {
  if (window.apmgsrnViewer) { return; }
  const viewer = {};
  window.apmgsrnViewer = viewer;

  // ------------------------------------------------------------------ server calls
  function ready() { return window.trame && window.trame.state && window.trame.client; }
  function call(name, args) {
    if (!ready()) { return Promise.resolve(null); }
    return window.trame.trigger(name, args || []);
  }
  viewer.call = call;

  // ------------------------------------------------------------------ camera
  let drag = null;
  function idle() { return { orbitX: 0, orbitY: 0, panX: 0, panY: 0, zoom: 0, end: false, reset: false }; }
  let pending = idle();
  let inFlight = false;
  function sendCamera() {
    if (inFlight) { return; }
    const p = pending;
    const hasMotion = p.orbitX || p.orbitY || p.panX || p.panY || p.zoom;
    if (!hasMotion && !p.end && !p.reset) { return; }
    pending = idle();
    inFlight = true;
    call("viewer_camera", [p.orbitX, p.orbitY, p.panX, p.panY, p.zoom, p.end, p.reset])
      .catch(function () {})
      .finally(function () { inFlight = false; sendCamera(); });
  }
  document.addEventListener("pointerdown", function (event) {
    const element = event.target.closest && event.target.closest("#apm-viewport");
    if (!element || event.target.closest("#apm-messages")) { return; }
    let mode = null;
    if (event.button === 1 || (event.button === 0 && event.shiftKey)) { mode = "pan"; }
    else if (event.button === 0) { mode = "orbit"; }
    if (!mode) { return; }
    event.preventDefault();
    try { element.setPointerCapture(event.pointerId); } catch (error) { /* synthetic events */ }
    drag = { x: event.clientX, y: event.clientY, mode: mode, element: element };
  });
  document.addEventListener("pointermove", function (event) {
    if (!drag) { return; }
    const box = drag.element.getBoundingClientRect();
    const dx = (event.clientX - drag.x) / Math.max(1, box.width);
    const dy = (event.clientY - drag.y) / Math.max(1, box.height);
    drag.x = event.clientX; drag.y = event.clientY;
    if (drag.mode === "pan") { pending.panX += dx; pending.panY += dy; }
    else { pending.orbitX += dx; pending.orbitY += dy; }
    sendCamera();
  });
  function endDrag() {
    if (!drag) { return; }
    drag = null;
    pending.end = true;
    sendCamera();
  }
  // Reset goes through the same queue, so motion still waiting to be sent can never land after it.
  viewer.resetView = function () {
    pending = idle();
    pending.reset = true;
    pending.end = true;
    sendCamera();
  };
  document.addEventListener("pointerup", endDrag);
  document.addEventListener("pointercancel", endDrag);
  document.addEventListener("wheel", function (event) {
    const element = event.target.closest && event.target.closest("#apm-viewport");
    if (!element) { return; }
    event.preventDefault();
    const lines = event.deltaMode === 1 ? 33 : (event.deltaMode === 2 ? 400 : 1);
    pending.zoom += event.deltaY * lines / 100.0;
    sendCamera();
  }, { passive: false });
  document.addEventListener("auxclick", function (event) {
    if (event.target.closest && event.target.closest("#apm-viewport")) { event.preventDefault(); }
  });

  // ------------------------------------------------------------------ downloads and uploads
  function download(name, base64, type) {
    const bytes = Uint8Array.from(atob(base64), function (c) { return c.charCodeAt(0); });
    const url = URL.createObjectURL(new Blob([bytes], { type: type }));
    const link = document.createElement("a");
    link.href = url; link.download = name;
    document.body.appendChild(link); link.click(); document.body.removeChild(link);
    setTimeout(function () { URL.revokeObjectURL(url); }, 2000);
  }
  viewer.saveFrame = function () {
    return call("viewer_save_frame", []).then(function (reply) {
      if (reply && reply.data) { download(reply.name, reply.data, "image/png"); }
      return reply;
    });
  };
  viewer.saveTransferFunction = function () {
    return call("viewer_save_transfer_function", []).then(function (reply) {
      if (reply && reply.data) { download(reply.name, reply.data, "application/json"); }
      return reply;
    });
  };
  viewer.chooseUpload = function () {
    const input = document.getElementById("apm-upload");
    if (input) { input.value = ""; input.click(); }
  };
  document.addEventListener("change", function (event) {
    if (!event.target || event.target.id !== "apm-upload") { return; }
    const file = event.target.files && event.target.files[0];
    if (!file) { return; }
    const limit = (window.trame.state.get("upload_limit") || 1048576);
    // upload_error is the page's own (never sent): the server would refuse the message anyway.
    window.trame.state.set("upload_error", "");
    if (file.size > limit) {
      window.trame.state.set("upload_error",
        file.name + ": " + file.size + " bytes is over the upload limit of " + limit + " bytes");
      return;
    }
    file.text().then(function (text) { call("viewer_upload_preset", [file.name, text]); });
  });

  // ------------------------------------------------------------------ opacity editor
  const editor = { points: [], dragging: -1, inFlight: false, queued: null, lastPress: null };
  const HEIGHT = 150, PAD = 8;
  function size() {
    const host = document.getElementById("apm-tf-editor");
    return { host: host, width: host ? Math.max(120, host.clientWidth) : 300 };
  }
  function toScreen(point, width) {
    return [PAD + point[0] * (width - 2 * PAD), PAD + (1 - point[1]) * (HEIGHT - 2 * PAD)];
  }
  function fromScreen(x, y, width) {
    const px = (x - PAD) / (width - 2 * PAD), py = 1 - (y - PAD) / (HEIGHT - 2 * PAD);
    return [Math.min(1, Math.max(0, px)), Math.min(1, Math.max(0, py))];
  }
  function sendPoints(interactive) {
    const points = editor.points.map(function (p) { return [p[0], p[1]]; });
    if (editor.inFlight) { editor.queued = interactive; return; }
    editor.inFlight = true;
    call("viewer_opacity", [points, interactive]).catch(function () {}).finally(function () {
      editor.inFlight = false;
      if (editor.queued !== null) { const again = editor.queued; editor.queued = null; sendPoints(again); }
    });
  }
  function draw() {
    const s = size();
    if (!s.host) { return; }
    const width = s.width;
    const svgNS = "http://www.w3.org/2000/svg";
    let svg = s.host.querySelector("svg");
    if (!svg) {
      svg = document.createElementNS(svgNS, "svg");
      svg.setAttribute("id", "apm-tf-svg");
      svg.style.touchAction = "none";
      svg.style.userSelect = "none";
      s.host.appendChild(svg);
      svg.addEventListener("pointerdown", onDown);
      svg.addEventListener("contextmenu", onDelete);
    }
    svg.setAttribute("width", width); svg.setAttribute("height", HEIGHT);
    svg.setAttribute("viewBox", "0 0 " + width + " " + HEIGHT);
    while (svg.firstChild) { svg.removeChild(svg.firstChild); }
    const background = document.createElementNS(svgNS, "rect");
    background.setAttribute("x", 0); background.setAttribute("y", 0);
    background.setAttribute("width", width); background.setAttribute("height", HEIGHT);
    background.setAttribute("fill", "#f4f4f4"); background.setAttribute("stroke", "#bbb");
    svg.appendChild(background);
    const histogram = window.trame.state.get("histogram") || [];
    const bins = histogram.length;
    for (let i = 0; i < bins; i++) {
      const bar = document.createElementNS(svgNS, "rect");
      const x0 = PAD + i / bins * (width - 2 * PAD), x1 = PAD + (i + 1) / bins * (width - 2 * PAD);
      const h = histogram[i] * (HEIGHT - 2 * PAD);
      bar.setAttribute("x", x0); bar.setAttribute("width", Math.max(0.5, x1 - x0 - 0.5));
      bar.setAttribute("y", HEIGHT - PAD - h); bar.setAttribute("height", h);
      bar.setAttribute("fill", "#c9c9d6");
      svg.appendChild(bar);
    }
    const line = document.createElementNS(svgNS, "polyline");
    line.setAttribute("points", editor.points.map(function (p) { return toScreen(p, width).join(","); }).join(" "));
    line.setAttribute("fill", "none"); line.setAttribute("stroke", "#303f9f"); line.setAttribute("stroke-width", 2);
    svg.appendChild(line);
    editor.points.forEach(function (p, index) {
      const c = toScreen(p, width);
      const dot = document.createElementNS(svgNS, "circle");
      dot.setAttribute("cx", c[0]); dot.setAttribute("cy", c[1]); dot.setAttribute("r", 6);
      dot.setAttribute("fill", index === editor.dragging ? "#ff7043" : "#303f9f");
      dot.setAttribute("stroke", "white"); dot.setAttribute("stroke-width", 1.5);
      dot.setAttribute("data-index", index);
      dot.setAttribute("class", "apm-tf-point");
      dot.style.cursor = "grab";
      svg.appendChild(dot);
    });
  }
  function localPosition(event) {
    const box = event.currentTarget.getBoundingClientRect();
    return [event.clientX - box.left, event.clientY - box.top];
  }
  function onDown(event) {
    if (event.button !== 0) { return; }
    event.preventDefault();
    const width = size().width;
    const at = localPosition(event);
    let index = -1;
    if (event.target && event.target.getAttribute && event.target.getAttribute("data-index") !== null) {
      index = parseInt(event.target.getAttribute("data-index"), 10);
      // A second press on the same point soon after the first deletes it. (The browser's dblclick
      // cannot be used: the first press redraws the points, so the two clicks hit different elements.)
      const now = Date.now();
      const last = editor.lastPress;
      editor.lastPress = { index: index, time: now };
      if (last && last.index === index && now - last.time < 400) {
        editor.lastPress = null;
        removePoint(index);
        return;
      }
    } else {
      editor.lastPress = null;
      // Empty space: a new point there (kept in position order).
      const point = fromScreen(at[0], at[1], width);
      editor.points.push(point);
      editor.points.sort(function (a, b) { return a[0] - b[0]; });
      index = editor.points.indexOf(point);
      sendPoints(true);
    }
    editor.dragging = index;
    const svg = event.currentTarget;
    try { svg.setPointerCapture(event.pointerId); } catch (error) { /* synthetic events */ }
    function move(moveEvent) {
      const box = svg.getBoundingClientRect();
      const p = fromScreen(moveEvent.clientX - box.left, moveEvent.clientY - box.top, width);
      // A point moves between its neighbours only, so the order (and the curve) stays a function.
      const low = editor.dragging > 0 ? editor.points[editor.dragging - 1][0] : 0;
      const high = editor.dragging < editor.points.length - 1 ? editor.points[editor.dragging + 1][0] : 1;
      p[0] = Math.min(high, Math.max(low, p[0]));
      editor.points[editor.dragging] = p;
      draw();
      sendPoints(true);
    }
    function up() {
      svg.removeEventListener("pointermove", move);
      svg.removeEventListener("pointerup", up);
      svg.removeEventListener("pointercancel", up);
      editor.dragging = -1;
      draw();
      sendPoints(false);
    }
    svg.addEventListener("pointermove", move);
    svg.addEventListener("pointerup", up);
    svg.addEventListener("pointercancel", up);
    draw();
  }
  function removePoint(index) {
    if (editor.points.length <= 1 || index < 0 || index >= editor.points.length) { return; }
    editor.points.splice(index, 1);
    editor.dragging = -1;
    draw();
    sendPoints(false);
  }
  function onDelete(event) {
    event.preventDefault();
    const attribute = event.target && event.target.getAttribute && event.target.getAttribute("data-index");
    if (attribute === null || attribute === undefined) { return; }
    removePoint(parseInt(attribute, 10));
  }
  viewer.opacityPoints = function () { return editor.points.map(function (p) { return [p[0], p[1]]; }); };

  function start() {
    if (!ready() || !document.getElementById("apm-tf-editor")) { setTimeout(start, 100); return; }
    window.trame.state.watch(["opacity_points", "histogram"], function (points) {
      if (editor.dragging < 0 && Array.isArray(points)) {
        editor.points = points.map(function (p) { return [p[0], p[1]]; });
      }
      draw();
    });
    // Vue may re-create the editor's host element (e.g. when the drawer re-renders): redraw into it.
    setInterval(function () {
      const host = document.getElementById("apm-tf-editor");
      const svg = host && host.querySelector("svg");
      if (host && (!svg || svg.getAttribute("width") != Math.max(120, host.clientWidth))) { draw(); }
    }, 500);
  }
  start();
})();
"""

VIEWER_STYLE = r"""
#apm-viewport {
  position: relative; width: 100%; height: calc(100vh - 48px); background: #e8e8ec;
  display: flex; align-items: center; justify-content: center; overflow: hidden;
  cursor: grab; touch-action: none; user-select: none;
}
#apm-viewport:active { cursor: grabbing; }
#apm-frame { max-width: 100%; max-height: 100%; width: auto; height: 100%; object-fit: contain;
  image-rendering: auto; pointer-events: none; }
#apm-overlay-svg { position: absolute; left: 0; top: 0; width: 100%; height: 100%; pointer-events: none; }
#apm-overlay-text { position: absolute; left: 12px; bottom: 10px; font: 12px monospace; color: #333;
  background: rgba(255, 255, 255, 0.75); padding: 4px 8px; border-radius: 4px; pointer-events: none;
  white-space: pre; }
#apm-tf-editor { width: 100%; }
#apm-messages { position: absolute; top: 8px; left: 8px; right: 8px; z-index: 5; cursor: default; }
.apm-section { font-size: 0.8rem; font-weight: 600; text-transform: uppercase; color: #555; margin: 10px 0 4px; }
"""
