// Ours, added to the rerun viewer's page (/rerun/, routes_rerun.neutralise_index). The Runs page
// opens the viewer in a tab of its own (noopener: a renderer process of its own), because a viewer
// embedded in the dashboard froze the dashboard's main thread for minutes on a software GPU and
// its WebSocket closed (issue 19 item 9, docs/logging/appliance.md). In its own tab the
// dashboard's key handler is not there, so this page keeps the promise "Esc stops from anywhere"
// itself (issue 19 item 1), with the dashboard's rule, over HTTP with the session cookie and the
// CSRF header: RUN or PAUSED -> the `stop` command; any other state of a live run -> end the run.
// It also follows the live stream to the next run, as the embedded viewer did, and offers the
// run's replay from its start: the live stream keeps only a short window and sends it newest
// first, so a viewer opened mid-run starts at the live edge (issue 31 bug 6, logs/rerun_servers.py
// LiveProxy); the whole run so far is its log, opened as .rrd in another viewer tab. From the
// page's load on (issue 31 bug 6): the viewer's wasm is compiled from its fetch, the live stream
// is asked for once the viewer's wasm is compiled, read in a worker, and handed to the viewer when
// it reads (what came meanwhile newest first) and has drawn a warm-up recording of ours (its plots'
// render pipelines built before the run's data, hidden, then closed), and a line says what the tab
// is doing until the first data is drawn (each below).
// The 3D view's tab (viser's page, server/http/viser.py) loads this script too, for Esc.
"use strict";
(function () {
  const FOLLOW_MS = 3000;
  let busy = false, noteTimer = null;

  // The rerun viewer's tab (not viser's): console.debug does nothing here. When the first plot is
  // drawn, the viewer's shader compiler (naga, logging at debug level in rerun's web build, with
  // no switch) writes ~9000 console.debug lines; each is a message to DevTools when a debugger
  // is attached and a message to the browser process in any case. Measured in chromium on the
  // CPU-only VM: it froze the tab 5-8 s on its first data, muted 2-3 s (issue 31 bug 6,
  // bench/appliance/rerun_lag.py). Runs before re_viewer.js (server/http/rerun.py puts this
  // script first), whose bindings look console.debug up at each call. The viewer's info,
  // warnings and errors still reach the console; the original is kept for whoever debugs.
  const rerunPage = location.pathname.startsWith("/rerun/");
  const consoleDebug = console.debug;
  let debugMuted = 0;
  if (rerunPage) console.debug = () => { debugMuted += 1; };

  // The viewer's wasm (43 MB), compiled from its fetch while the page still loads (issue 31 bug 6).
  // rerun's index.html read it through a stream of its own (for a percentage), deleted
  // WebAssembly.instantiateStreaming and compiled the whole array buffer after the download, at
  // every opening: chromium keeps a compiled module only for one compiled from the fetched
  // response (its code cache, beside the HTTP cache's copy: a second opening skips compiling).
  // The prepared index.html hands this promise to the viewer's loader (server/http/rerun.py
  // _LOADER_OURS); if streaming fails (an odd proxy's content type), the loader gets the fetch
  // itself and compiles the old way. Measured: bench/appliance/rerun_lag.py "where the time went".
  const WASM = "/rerun/re_viewer_bg.wasm";
  const wasm = rerunPage && typeof WebAssembly.compileStreaming === "function"
    ? WebAssembly.compileStreaming(fetch(WASM, { credentials: "same-origin" })).catch(() => fetch(WASM, { credentials: "same-origin" }))
    : null;
  let wasmReady = !wasm;  // the viewer's code is loaded (and compiled): the line's "loading" step ends
  if (wasm) wasm.then(() => { wasmReady = true; }, () => { wasmReady = true; });

  async function post(path, body) {
    const { data, res } = await xrfLib.send("POST", path, body || {});  // frontend/lib.js, loaded before this
    const detail = typeof data.detail === "string" ? data.detail : data.detail ? JSON.stringify(data.detail) : res.statusText;
    return { ok: res.ok, status: res.status, data, detail };
  }

  // A status line of ours over the viewer (the canvas covers the whole page, so it floats above
  // it): element `id`, made with `style` the first time.
  function floating(id, style) {
    let box = document.getElementById(id);
    if (!box) {
      box = document.createElement("div");
      box.id = id;
      box.setAttribute("role", "status");
      Object.assign(box.style, { position: "fixed", borderRadius: "6px", pointerEvents: "none" }, style);
      // (before the page's body exists: the live tab's line is drawn from this script's start on)
      (document.body || document.documentElement).appendChild(box);
    }
    return box;
  }

  // A short note over the viewer.
  function note(text, bad) {
    const n = floating("xrf-stop-note", { top: "12px", left: "50%", transform: "translateX(-50%)",
      zIndex: "2147483647", padding: "8px 16px", font: "600 15px system-ui, sans-serif",
      color: "#fff", boxShadow: "0 2px 8px rgba(0,0,0,.4)" });
    n.textContent = text;
    n.dataset.kind = bad ? "refused" : "sent";
    n.style.background = bad ? "#b91c1c" : "#15803d";
    n.style.display = "block";
    clearTimeout(noteTimer);
    noteTimer = setTimeout(() => { n.style.display = "none"; }, bad ? 10000 : 6000);
  }

  async function stop() {
    if (busy) return;  // a held key repeats: one stop at a time
    busy = true;
    note("Esc: sending stop…");  // at once: the viewer may keep this thread busy until the answer is handled
    try {
      const r = await post("/api/runs/current/command", { cmd: "stop" });
      if (r.status === 401) { note("Not logged in: log in to the dashboard again, then stop from there.", true); return; }
      if (!r.ok) { note("Stop refused: " + r.detail, true); return; }
      if (r.data.accepted) { note("Stop sent (Esc): the controller is stopping."); return; }
      // Not in RUN or PAUSED: the loop refuses `stop`, and the rule ends the run instead.
      note("Ending the run (Esc): it is in " + (r.data.state_name || "another state") + "…");
      const end = await post("/api/runs/current/stop");
      if (end.ok) note("Run ended (Esc): it was in " + (r.data.state_name || "another state") + ".");
      else note("Could not end the run: " + end.detail, true);
    } catch (e) {
      note("Stop not sent: the appliance does not answer (" + e.message + "). Use the STOP button of the bench.", true);
    } finally {
      busy = false;
    }
  }

  // Capture phase on the window: before the viewer's canvas (a wasm app) can take the key.
  window.addEventListener("keydown", (ev) => {
    if (ev.key !== "Escape") return;  // only Esc: other keys are the viewer's
    ev.preventDefault();
    if (!ev.repeat) stop();
  }, true);

  // The live stream (?url=rerun+http(s)://<host>/proxy) is the latest run's: when a new run starts,
  // the previous run's stream ends, and this tab reloads onto the new one.
  const url = new URLSearchParams(location.search).get("url") || "";
  const live = /^rerun\+https?:\/\/[^/]+\/proxy$/.test(url);

  // The live view's canvas is smaller than the tab by default: chromium without a GPU driver
  // rasterises every pixel of the canvas on the CPU each frame, and while it follows live data
  // the viewer redraws every frame, so the frame time (and with it how far behind live the plots
  // are) follows the pixel count (issue 31 bug 6, bench/appliance/README.md). The viewer sizes its
  // canvas's pixels from the canvas's CSS box, so a smaller box is fewer pixels (not a scaled
  // image: its mouse input stays right). "Full size" is one click away, remembered per browser.
  const LIVE_CANVAS = { width: 800, height: 500 };  // CSS px
  const FULL_KEY = "xrf-rerun-live-full";
  let full = false;
  try { full = localStorage.getItem(FULL_KEY) === "1"; } catch (e) { /* storage off: the default */ }
  const fullSize = () => full;
  function sizeCanvas() {
    let st = document.getElementById("xrf-canvas-size");
    if (!st) {
      st = document.createElement("style");
      st.id = "xrf-canvas-size";
      document.head.appendChild(st);
    }
    st.textContent = fullSize() ? "" : `#the_canvas_id { width: min(100%, ${LIVE_CANVAS.width}px) !important; `
      + `height: min(100%, ${LIVE_CANVAS.height}px) !important; }`;
    const b = document.getElementById("xrf-canvas-toggle");
    if (b) b.textContent = fullSize() ? "Smaller view (faster without a GPU)" : "Full-size view";
  }
  if (live) sizeCanvas();

  // for the test and the benchmark: frames drawn and asked for by the viewer, reads of the live
  // stream with data; when the stream was asked for (by this script, see below), when the viewer
  // asked for it, when its first data was read
  const frames = { drawn: 0, asked: 0, data: 0, held: 0, streamAt: null, viewerAskedAt: null, answeredAt: null, firstDataAt: null, early: "none",
    heldGroups: 0, heldFrames: 0, heldNewestAgeMs: null, worker: null };  // (what the early stream brought before the viewer read it, below)
  const held = new Map();  // our id -> the viewer's callback, waiting for a reason to draw
  let onData = () => {};  // the frame gate's (below): the stream brought data
  let freeFrames = () => {};  // the frame gate's (below): every frame the viewer asks for drawn, for a while

  // The live stream, asked for just before the viewer asks (issue 31 bug 6): the viewer asks for
  // it only once its app has started (wasm compiled and started: 1.5-3 s on a 2-core machine
  // without a GPU, more under load). So this script sends the very request the viewer sends
  // (ReadMessages, an empty request, gRPC-web) as soon as the viewer's wasm is compiled, 0.7-0.9 s
  // before the viewer asks, and when the viewer asks it gets this response. Not at the page's
  // load (as at first): the earlier the connection, the more the viewer's first frames have to
  // ingest before the newest samples (session 10). Only the first identical request, on this
  // origin; anything else goes to the network as asked. Not claimed within EARLY_MAX_MS: closed.
  // (The run's recording starts when this page is served, server-side.)
  //
  // The response is read in a Worker of its own (session 13), not on this page's thread: that
  // thread is the viewer's, busy for 0.5-3 s with the viewer's start (instantiating its wasm,
  // its first frames in software WebGL), and a read on it came when the thread was free, not when
  // the bytes came: the proxy's window and the batches after it, which came seconds apart, were
  // read as one, in the order they came, and the viewer's first frame drew the window, the oldest
  // (session 12: 2.16 s behind live). The worker reads each batch when it comes and keeps it
  // with that time (bursts within GROUP_MS: the window, or one batch of the recording). What it
  // holds goes to the viewer at the viewer's first read (taken then: what came while this thread
  // was busy waited in the worker, where it can still be put in order), newest first: what is not
  // the run's recorded data (store info, the blueprint) in the order it came, then the
  // recording's bursts, the latest first (each burst's messages in the order they came: the
  // proxy sends its window newest first), then the trailers if the stream ended. The viewer
  // ingests ~10 ms of messages per frame: its first frame takes the newest. From then on the
  // worker sends each read as it comes (taken at each of the viewer's reads instead, the batches
  // after the first waited for this thread twice each, and a viewer's first frame with data drew
  // a sample 1.1 s old at its start: bench/README.md, session 13). A burst older than DROP_MS (the
  // live plots' span) before the newest held is dropped (the first burst, with the recording's
  // static data, is kept): the live view is a display, every sample is in the run's log (the
  // replay link). The bytes are moved between the threads, not copied.
  const STREAM_PATH = "/rerun.sdk_comms.v1alpha1.MessageProxyService/ReadMessages";
  const EMPTY_READ = new Uint8Array(5);  // one gRPC-web data frame holding an empty ReadMessagesRequest
  const EARLY_MAX_MS = 120000;
  const GROUP_MS = 100, DROP_MS = 10000;  // DROP_MS: logs/rerun_live.py LIVE_SPAN_S
  // A reply of the worker handled this late was waited on by this thread: what came meanwhile is
  // newer, and is asked for before the reply is handed on (STALE_MS after it was sent).
  const STALE_MS = 50;
  const nativeFetch = window.fetch.bind(window);
  const pageRaf = window.requestAnimationFrame.bind(window);  // (before the frame gate's, below)
  let early = null;

  // The worker's code (a blob: the viewer's CSP allows `worker-src blob:`; these functions' source).
  function recordingChunk(payload) {  // ReadMessagesResponse{log_msg=1: LogMsg{arrow_msg=2: {store_id=1: {kind=1}}}}, kind 1: a recording
    let rec = false;
    const inner = (field, each) => (f, v) => { if (f === field && typeof v !== "number") protoFields(v, each); };
    protoFields(payload, inner(1, inner(2, inner(1, (f, v) => { if (f === 1 && v === 1) rec = true; }))));
    return rec;
  }
  function streamWorker() {
    // messages: {ask: {url, groupMs, dropMs}}: read the stream; "take": hand over what is held
    // (at once if anything is, else as soon as something comes); "takeNow": at once, held or not;
    // "stream": from now on, each read as it comes; "abort". Posts {head}, then per take (and per
    // read once streaming) {data, other, trailers, groups, newestAt, at, end}.
    let ctl = null, opt = null, ended = null, notify = false, streaming = false, lastRead = -Infinity;
    let groups = [], other = [], trailers = [], rest = new Uint8Array(0);
    const wall = () => performance.timeOrigin + performance.now();
    const marks = { started: wall() };  // (for the benchmark: when the worker ran, was asked, answered, first read)
    function take(now) {  // now: answer even with nothing held (else once something comes)
      const data = [];
      for (let i = groups.length - 1; i >= 0; i--) data.push(...groups[i].data);  // the latest burst first
      if (!now && !data.length && !other.length && !trailers.length && ended === null) { notify = true; return; }
      const newestAt = groups.length ? groups[groups.length - 1].at : null;
      const out = { data, other, trailers, groups: groups.length, newestAt, at: wall(), end: ended };
      const moved = [...new Set([...data, ...other, ...trailers].map((f) => f.buffer))];
      groups = []; other = []; trailers = [];
      // each frame a view of a read's own buffer (or of a copy): moved, not copied
      postMessage(out, moved);
    }
    function drop(now) {  // bursts older than the live plots' span, but the first (static data)
      const keep = groups.filter((g, i) => (g.first && i === 0) || now - g.at <= opt.dropMs);
      groups = keep;
    }
    async function read(res) {
      const reader = res.body.getReader();
      let first = true;
      for (;;) {
        const { done, value } = await reader.read();
        if (done) return;
        const now = wall();
        if (!marks.firstRead) { marks.firstRead = now; postMessage({ marks }); }
        if (now - lastRead > opt.groupMs || !groups.length) { groups.push({ at: now, data: [], first }); first = false; }
        lastRead = now;
        const group = groups[groups.length - 1];
        group.at = now;
        let buf = value, i = 0;
        if (rest.length) { buf = new Uint8Array(rest.length + value.length); buf.set(rest); buf.set(value, rest.length); }
        while (buf.length - i >= 5) {
          const n = ((buf[i + 1] << 24) >>> 0) + (buf[i + 2] << 16) + (buf[i + 3] << 8) + buf[i + 4];
          if (buf.length - i - 5 < n) break;
          const frame = buf.subarray(i, i + 5 + n);
          if (buf[i] & 0x80) trailers.push(frame);
          else (recordingChunk(frame.subarray(5)) ? group.data : other).push(frame);
          i += 5 + n;
        }
        rest = buf.slice(i);  // a copy: the frames' buffer is moved whole
        drop(now);
        if (streaming || notify) { notify = false; take(true); }
      }
    }
    onmessage = async (ev) => {
      const m = ev.data;
      if (m === "take" || m === "takeNow") { take(m === "takeNow"); return; }
      if (m === "stream") {
        streaming = true;
        if (groups.length || other.length || trailers.length || ended !== null) take(true);
        return;
      }
      if (m === "abort") { if (ctl) ctl.abort(); return; }
      if (!m.ask || ctl) return;
      opt = m.ask;
      marks.asked = wall();
      ctl = new AbortController();
      let res;
      try {
        res = await fetch(opt.url, {
          method: "POST", credentials: "same-origin", cache: "no-store", signal: ctl.signal, body: new Uint8Array(5),
          headers: { "content-type": "application/grpc-web+proto", "x-grpc-web": "1" },
        });
      } catch (err) {
        postMessage({ head: { error: String(err && err.message || err) } });
        return;
      }
      marks.answered = wall();
      postMessage({ head: { status: res.status, statusText: res.statusText, headers: [...res.headers] }, marks });
      try {
        if (res.body) await read(res);
        ended = "done";
      } catch (err) {
        ended = String(err && err.message || err);
      }
      if (streaming || notify) { notify = false; take(true); }
    };
  }

  // The worker is started with the page, not when the stream is asked for: chromium starts a
  // worker with tasks on this page's thread, and when the wasm is compiled that thread is about to
  // be busy with the viewer's start (measured: a worker made then fetched only after it).
  let streamReader = null;
  function startWorker() {
    try {
      const src = [protoFields, recordingChunk, streamWorker].map(String).join("\n") + "\nstreamWorker();";
      const blobUrl = URL.createObjectURL(new Blob([src], { type: "text/javascript" }));
      streamReader = new Worker(blobUrl);
      setTimeout(() => URL.revokeObjectURL(blobUrl), 60000);  // (once the worker has surely loaded it)
    } catch (err) {
      streamReader = null;  // no worker (an old browser, a stricter policy): the viewer asks for the stream itself
    }
  }
  function askEarly() {
    if (early || frames.viewerAskedAt !== null || frames.early !== "none") return;  // the viewer asked already
    const worker = streamReader;
    if (!worker) return;
    const e = { worker, replies: [], waiting: null, push: null, done: false };
    e.response = new Promise((resolve, reject) => {
      worker.onmessage = (ev) => {
        const m = ev.data;
        if (m.head) {
          frames.worker = m.marks || null;
          if (m.head.error) reject(new TypeError(m.head.error));
          else resolve(m.head);
        } else if (m.marks) frames.worker = m.marks;
        else if (m.data && e.push) e.push(m);
        else if (m.data) gotReply(e, m);
      };
      worker.onerror = () => reject(new TypeError("the live stream's worker failed"));
    });
    e.response.catch(() => {});  // the viewer reports a failed stream when it reads it
    worker.postMessage({ ask: { url: location.origin + STREAM_PATH, groupMs: GROUP_MS, dropMs: DROP_MS } });
    e.timer = setTimeout(() => { if (early === e) { closeEarly(e); early = null; frames.early = "closed"; } }, EARLY_MAX_MS);
    early = e;
    frames.streamAt = Date.now();
    frames.early = "asked";
  }
  function closeEarly(e) {
    e.done = true;
    clearTimeout(e.timer);
    e.worker.postMessage("abort");
    e.worker.terminate();
  }
  // The first take's reply: handed to the viewer's read, unless this thread handled it STALE_MS or
  // more after the worker sent it (the thread was busy: more may have come since, newer): then the
  // worker is asked again (twice at most: a thread always that slow gets what there is), and the
  // newer reply goes first.
  function gotReply(e, m) {
    e.replies.unshift(m);
    const stale = performance.timeOrigin + performance.now() - m.at >= STALE_MS;
    if (m.end === null && stale && e.replies.length < 3) { e.worker.postMessage("takeNow"); return; }
    const replies = e.replies;  // newest first
    e.replies = [];
    if (e.waiting) e.waiting(replies);
    e.waiting = null;
  }
  // The viewer's response: its body's first read takes what the worker holds, newest first (above);
  // from then on the worker sends each read as it comes, put in the body at once (the viewer reads
  // as it wants, as from the network).
  function handOver(e, head) {
    if (head.status < 200 || head.status > 299) { closeEarly(e); return new Response(null, head); }
    let sink = null, firstTake = true;
    const put = (replies) => {  // (replies: the newest first)
      const oldestFirst = [...replies].reverse();
      const other = oldestFirst.flatMap((r) => r.other), trailers = oldestFirst.flatMap((r) => r.trailers);
      const data = replies.flatMap((r) => r.data);
      for (const f of [...other, ...data, ...trailers]) sink.enqueue(f);
      const end = replies.find((r) => r.end !== null);
      if (end) {
        e.push = null;
        closeEarly(e);
        if (end.end === "done") sink.close();
        else sink.error(new TypeError(end.end));
      }
      return data.length + other.length;
    };
    const body = new ReadableStream({
      start(controller) { sink = controller; },
      pull() {  // the viewer reads (the first time: what is held, newest first; later: a no-op)
        if (!firstTake || e.done) return undefined;
        firstTake = false;
        // not before the viewer has drawn its warm-up (below): then the newest batch is taken
        return warmedUp().then(() => new Promise((resolve) => {
          e.waiting = resolve;
          e.worker.postMessage("take");
        })).then((replies) => {
          frames.heldGroups = replies.reduce((n, r) => n + r.groups, 0);
          const newest = replies.find((r) => r.newestAt !== null);
          frames.heldNewestAgeMs = newest ? performance.timeOrigin + performance.now() - newest.newestAt : null;
          frames.heldFrames = put(replies);
          if (e.done) return;
          e.push = (m) => put([m]);
          e.worker.postMessage("stream");
        });
      },
      cancel() { closeEarly(e); },
    }, { highWaterMark: 0 });
    return new Response(body, head);
  }
  if (live && url.replace(/^rerun\+/, "").replace(/\/proxy$/, "") === location.origin) {
    // As soon as the module is compiled (the loader instantiates it, the app starts ~0.5 s later and
    // asks ~0.2-0.6 s after that): ~0.7-0.9 s ahead of the viewer. (Without a compiled module: at
    // the page's load.) Read by the worker (above), started now.
    startWorker();
    if (wasm) wasm.then(askEarly, askEarly); else askEarly();
  }
  async function bodyOf(args) {  // the request body of a fetch(...) call, or null
    try {
      if (args[0] instanceof Request) return new Uint8Array(await args[0].clone().arrayBuffer());
      const b = args[1] && args[1].body;
      if (b instanceof ArrayBuffer || ArrayBuffer.isView(b)) return new Uint8Array(b.buffer || b, b.byteOffset || 0, b.byteLength);
    } catch (e) { /* not readable: not ours */ }
    return null;
  }
  async function streamFetch(args) {
    const body = early ? await bodyOf(args) : null;
    const method = (args[0] instanceof Request ? args[0].method : (args[1] && args[1].method) || "GET").toUpperCase();
    if (early && method === "POST" && body && body.length === EMPTY_READ.length && body.every((b) => b === 0)) {
      const e = early;
      early = null;
      clearTimeout(e.timer);
      frames.early = "used";
      const signal = args[0] instanceof Request ? args[0].signal : args[1] && args[1].signal;
      if (signal) signal.addEventListener("abort", () => closeEarly(e), { once: true });
      // (the worker's request failed: the viewer's own goes to the network, as without it)
      return e.response.then((head) => handOver(e, head), () => { closeEarly(e); return nativeFetch(...args); });
    }
    if (early) { closeEarly(early); early = null; frames.early = "not used"; }
    return nativeFetch(...args);
  }

  if (live) {
    // The live stream's reads only (not the page's download of the viewer's wasm, read the same way).
    const streams = new WeakSet(), readers = new WeakSet();
    window.fetch = (...args) => {
      const url = String(args[0] instanceof Request ? args[0].url : args[0]);
      if (!url.endsWith(STREAM_PATH)) return nativeFetch(...args);
      frames.viewerAskedAt ??= Date.now();
      frames.streamAt ??= frames.viewerAskedAt;
      return streamFetch(args).then((res) => {
        frames.answeredAt ??= Date.now();
        if (res.body) streams.add(res.body);
        return res;
      });
    };
    const nativeGetReader = ReadableStream.prototype.getReader;
    ReadableStream.prototype.getReader = function (...args) {
      const reader = nativeGetReader.apply(this, args);
      if (streams.has(this)) readers.add(reader);
      return reader;
    };
    const nativeRead = ReadableStreamDefaultReader.prototype.read;
    ReadableStreamDefaultReader.prototype.read = function (...args) {
      const got = nativeRead.apply(this, args);
      if (!readers.has(this)) return got;
      return got.then((r) => {
        if (!r.done) {
          frames.data += 1;
          const first = frames.firstDataAt === null;
          if (first) frames.firstDataAt = Date.now();
          onData(first);
        }
        return r;
      });
    };
  }

  // Frames when there is something new to show (issue 31 bug 6). While it follows live data the
  // viewer asks for a frame every frame, and without a GPU driver each frame of the live canvas
  // costs chromium's GPU process ~0.3 CPU-seconds (SwiftShader): measured 3-4.5 frames/s using 1.5
  // of this 2-core machine, for a stream that changes twice a second (logs/rerun_live.py
  // SEND_PERIOD_S). So in the live tab a frame the viewer asks for is drawn at once when the
  // stream brought data since the last frame (a little later, so one frame takes a whole batch),
  // when the person uses mouse or keyboard (for FREE_MS after), in the stream's first FREE_MS
  // (the replayed window: the viewer ingests ~10 ms of messages per frame), and otherwise
  // IDLE_FRAME_MS after the last one began (a frame slower than that is followed at once: on a
  // loaded machine the viewer gets every frame it can, as without this). The viewer ingests data only in a frame, so this is also what
  // keeps it at the live edge: a frame follows each batch. rerun's web viewer has no frame-rate
  // setting; it asks for frames with window.requestAnimationFrame and reads the stream with
  // ReadableStreamDefaultReader.read, looked up at each call, so both are wrapped before it loads.
  const IDLE_FRAME_MS = 500, FREE_MS = 3000, SETTLE_MS = 40;
  // Every frame the viewer asks for, as before (to compare: bench/appliance/rerun_lag.py --all-frames).
  let allFrames = false;
  try { allFrames = localStorage.getItem("xrf-rerun-live-frames") === "all"; } catch (e) { /* storage off */ }
  if (live && !allFrames) {
    const nativeRaf = window.requestAnimationFrame.bind(window);
    const nativeCancel = window.cancelAnimationFrame.bind(window);
    const passed = new Map();  // our id -> chromium's id, once asked for
    let nextId = 1, lastFrame = 0, fresh = false, freeUntil = 0, timer = null;
    const draw = (id, cb) => {
      passed.set(id, nativeRaf((t) => {
        passed.delete(id);
        lastFrame = performance.now();
        fresh = false;
        frames.drawn += 1;
        cb(t);
      }));
    };
    const releaseAll = () => {
      clearTimeout(timer);
      timer = null;
      for (const [id, cb] of held) { held.delete(id); draw(id, cb); }
    };
    // a slow frame (a loaded machine: frames seconds apart) is followed at once, never held
    const due = () => fresh || performance.now() < freeUntil || performance.now() - lastFrame >= IDLE_FRAME_MS;
    const schedule = () => {  // held callbacks drawn after IDLE_FRAME_MS at the latest
      if (timer !== null || !held.size) return;
      timer = setTimeout(releaseAll, Math.max(0, lastFrame + IDLE_FRAME_MS - performance.now()));
    };
    window.requestAnimationFrame = (cb) => {
      const id = nextId++;
      frames.asked += 1;
      if (due()) draw(id, cb);
      else { held.set(id, cb); schedule(); }
      return id;
    };
    window.cancelAnimationFrame = (id) => {
      held.delete(id);
      if (passed.has(id)) { nativeCancel(passed.get(id)); passed.delete(id); }
    };
    const wake = (ms) => {
      freeUntil = Math.max(freeUntil, performance.now() + ms);
      releaseAll();
    };
    freeFrames = () => wake(FREE_MS);
    onData = (first) => {
      if (first) wake(FREE_MS);
      else if (!fresh) { fresh = true; clearTimeout(timer); timer = setTimeout(releaseAll, SETTLE_MS); }
    };
    for (const ev of ["pointerdown", "pointermove", "pointerup", "wheel", "keydown", "keyup", "resize", "focus"]) {
      window.addEventListener(ev, () => wake(FREE_MS), { capture: true, passive: true });
    }
  }
  if (live) {
    // rerun's welcome screen (its examples) is drawn until a recording arrives: not for a live view.
    const q = new URLSearchParams(location.search);
    if (!q.has("hide_welcome_screen")) {
      q.set("hide_welcome_screen", "");
      history.replaceState(history.state, "", location.pathname + "?" + q.toString() + location.hash);
    }
  }
  // What the live tab shows before its first plot (issue 31 bug 6): the viewer's canvas is empty
  // until its app has started and drawn the stream's first data, seconds on a machine without a
  // GPU; empty plots looked like a run with no data. A line over the canvas says which step it is
  // at, and goes once the viewer has drawn a frame holding the run's first sample (holdsSample).
  let liveRun = null, statusTimer = null;
  // Whether the viewer holds a sample of a run yet (issue 31 bug 6: the line stays until the first
  // sample is drawn; the stream's first bytes are its store info and blueprint, plots still
  // empty). From its own state, window._handle.viewer_state(): an encoded GetViewerStateResponse
  // (rerun's viewer_control.proto, 0.41): recordings = 3, each {store_id = 1, timelines = 2}, a
  // timeline {timeline = 1, time_range = 3}: a recording's timeline has a range once it holds a
  // sample (tests/xrf_testing/rerun_stream.py reads the same). A viewer without it: the first data.
  function protoFields(buf, each) {  // protobuf wire format: each(field, varint or bytes)
    let i = 0;
    const varint = () => { let v = 0, m = 1, b; do { b = buf[i++]; v += (b & 0x7f) * m; m *= 128; } while (b & 0x80 && i < buf.length); return v; };
    while (i < buf.length) {
      const key = varint(), field = Math.floor(key / 8), wire = key % 8;
      if (wire === 0) each(field, varint());
      else if (wire === 2) { const n = varint(); each(field, buf.subarray(i, i + n)); i += n; }
      else if (wire === 1) i += 8;
      else if (wire === 5) i += 4;
      else return;  // not what we read: stop
    }
  }
  // The recordings in the viewer's state (store id -> whether it holds a sample yet), or null
  // when the viewer has no state to give.
  function recordings() {
    let state;
    try { state = window._handle.viewer_state(); } catch (e) { return null; }
    const out = new Map();
    protoFields(new Uint8Array(state), (f, rec) => {
      if (f !== 3 || typeof rec === "number") return;
      let id = "", sample = false;
      protoFields(rec, (g, v) => {
        if (g === 1 && typeof v !== "number") id = new TextDecoder().decode(v);
        if (g === 2 && typeof v !== "number") protoFields(v, (h) => { if (h === 3) sample = true; });
      });
      out.set(id, sample);
    });
    return out;
  }
  // (the warm-up's recording is not the run's: below)
  function holdsSample() {
    const recs = recordings();
    if (recs === null) return frames.firstDataAt !== null;
    return [...recs].some(([id, sample]) => sample && id !== WARMUP_STORE);
  }

  // The warm-up (issue 31 bug 6, session 14). Without a GPU driver the viewer's first frame with
  // plots took 0.5-1.2 s by itself, and it was the frame with the run's first data: the viewer makes
  // its render pipelines when it first draws plots (7 WebGL programs, 14 shaders compiled by SwiftShader on
  // the CPU), so the samples it drew were that much older when they reached the screen
  // (bench/README.md, session 13). So before the run's data, the viewer draws a small recording of
  // our own with the kind of view the live blueprint has (a time-series plot of two series, made by
  // the appliance: logs/rerun_warmup.py, GET /api/logs/rerun/warmup.rrd), given to it through a channel
  // of its own (WebHandle.open_channel / send_rrd_to_channel) as soon as its app has started
  // (index.html calls appStarted, server/http/rerun.py). Once a frame has drawn it, the recording is
  // closed (viewer_control: close, by its store id) and only then is the run's stream handed over
  // (handOver: the worker holds it meanwhile, and the newest batch goes first): the pipelines stay,
  // and the frame with the run's first data draws with them. A person never sees the warm-up's
  // made-up samples: the canvas is hidden (opacity 0: the viewer still draws, and a click still
  // focuses it, so Esc from inside the viewer stops the run during the warm-up too; `visibility`
  // made it unfocusable: tests/ui/test_practical_ui.py) from before the
  // warm-up is given to the viewer until the viewer no longer holds it, the tab's line saying
  // "preparing the plots" meanwhile, and it is a recording of another application
  // (WARMUP_STORE), never mixed into the run's. If anything fails or takes longer than
  // WARMUP_MAX_MS, the run's stream is handed over anyway (as before the warm-up).
  const WARMUP_PATH = "/api/logs/rerun/warmup.rrd";
  const WARMUP_CHANNEL = "xrf-warmup";
  const WARMUP_STORE = "Recording:xrflab-warmup:warmup";  // logs/rerun_warmup.py: {kind}:{application}:{recording}
  const WARMUP_MAX_MS = 8000;
  const warmup = { state: "none", sentAt: null, drawnAt: null, closedAt: null, error: "" };
  frames.warmup = warmup;
  let warmupDone = null, warmupEnd = () => {};
  if (live) {
    warmup.state = "waiting";
    warmupDone = new Promise((resolve) => { warmupEnd = resolve; });
  }
  const warmupBytes = live
    ? nativeFetch(WARMUP_PATH, { credentials: "same-origin" }).then((r) => (r.ok ? r.arrayBuffer() : null)).catch(() => null)
    : null;
  function hideCanvas(hide) {
    let st = document.getElementById("xrf-warmup-hide");
    if (!st) {
      st = document.createElement("style");
      st.id = "xrf-warmup-hide";
      document.head.appendChild(st);
    }
    st.textContent = hide ? "#the_canvas_id { opacity: 0 !important; }" : "";
  }
  function pbBytes(field, bytes) {  // a length-delimited protobuf field
    const out = [field << 3 | 2];
    for (let n = bytes.length; ; n = Math.floor(n / 128)) { if (n < 128) { out.push(n); break; } out.push(n % 128 | 128); }
    return [...out, ...bytes];
  }
  // ViewerControlRequest{close = 1: CloseRequest{store_ids = 3: ViewerRecordingIds{store_ids = 1}}}
  // (rerun 0.41's viewer_control.proto)
  const CLOSE_WARMUP = new Uint8Array(pbBytes(1, pbBytes(3, pbBytes(1, [...new TextEncoder().encode(WARMUP_STORE)]))));
  const nextFrame = () => new Promise((resolve) => pageRaf(resolve));
  async function framesUntil(ok, deadline) {  // browser frames (the viewer's free) until ok(), or the deadline
    while (!ok()) {
      if (Date.now() > deadline) return false;
      freeFrames();
      await nextFrame();
    }
    return true;
  }
  async function appStarted(handle) {
    if (warmup.state !== "waiting") return;
    const started = Date.now(), deadline = started + WARMUP_MAX_MS;
    const address = location.href;
    warmup.state = "fetching";
    const bytes = await warmupBytes;
    if (!bytes) { warmup.state = "skipped"; warmup.error = "no warm-up recording"; warmupEnd(); return; }
    hideCanvas(true);
    try {
      handle.open_channel(WARMUP_CHANNEL, "XRF Lab warm-up");
      handle.send_rrd_to_channel(WARMUP_CHANNEL, new Uint8Array(bytes));
    } catch (e) {
      warmup.state = "failed";
      warmup.error = String(e && e.message || e);
      hideCanvas(false);
      warmupEnd();
      return;
    }
    warmup.state = "sent";
    warmup.sentAt = Date.now();
    // drawn: a frame ended holding the warm-up's samples (the viewer may draw the plots in that frame
    // or the next: measured, a frame or two after), and two more after it
    const has = () => { const r = recordings(); return r !== null && r.get(WARMUP_STORE) === true; };
    if (await framesUntil(has, deadline)) {
      for (let i = 0; i < 2; i++) { freeFrames(); await nextFrame(); }
      warmup.drawnAt = Date.now();
      warmup.state = "drawn";
    } else warmup.error = "not drawn in time";
    // Closed whatever happened, and the canvas shown only then: made-up samples are never on
    // screen, and the run's recording is the only one in the viewer. (Tried again until the viewer
    // no longer holds it; the run's stream is handed over meanwhile after WARMUP_MAX_MS.)
    const drawn = warmup.state === "drawn";
    for (let tries = 1; ; tries++) {
      try {
        freeFrames();
        await handle.viewer_control(CLOSE_WARMUP);
      } catch (e) {
        warmup.error = String(e && e.message || e);
      }
      const r = recordings();
      if (r !== null && !r.has(WARMUP_STORE)) break;
      if (tries === 3) { warmup.state = "not closed"; warmupEnd(); }
      await new Promise((resolve) => setTimeout(resolve, tries < 3 ? 0 : 1000));
    }
    try { handle.close_channel(WARMUP_CHANNEL); } catch (e) { /* closed with its recording */ }
    if (location.href !== address) history.replaceState(history.state, "", address);  // (the viewer's history)
    warmup.closedAt = Date.now();
    warmup.state = drawn ? "done" : "closed undrawn";
    hideCanvas(false);
    warmupEnd();
  }
  // What the first hand-over of the run's stream waits for: the warm-up's end, at most WARMUP_MAX_MS.
  // A stream read before the viewer's app has started (not seen: the app reads it once started) is
  // handed over at once, and then there is no warm-up: made after the run's data, it would be
  // drawn instead of it.
  function warmedUp() {
    if (warmup.state === "waiting") {
      warmup.state = "skipped";
      warmup.error = "the stream was read before the app started";
      warmupEnd();
    }
    if (!warmupDone) return Promise.resolve();
    return Promise.race([warmupDone, new Promise((resolve) => setTimeout(resolve, WARMUP_MAX_MS))]);
  }

  function liveStatus() {
    const box = floating("xrf-live-status", { top: "40px", left: "16px", zIndex: "2147483646",
      padding: "6px 12px", font: "14px system-ui, sans-serif", color: "#e5e7eb",
      background: "rgba(17,24,39,.9)" });
    const what = liveRun === null ? "Live plots" : `Live plots of run ${liveRun}`;
    let step;
    if (window._handle === undefined && !wasmReady) { step = "loading"; box.textContent = `${what}: loading the viewer…`; }
    else if (window._handle === undefined) { step = "starting"; box.textContent = `${what}: starting the viewer…`; }
    else if (warmup.state === "not closed") {
      // (not seen: the viewer kept its warm-up after three closes; the canvas stays hidden rather
      // than show made-up samples, and the person is told what helps)
      step = "preparing"; box.textContent = `${what}: the viewer did not let go of its warm-up plots; close this tab and open Live plots again`;
    } else if (warmup.state === "fetching" || warmup.state === "sent" || warmup.state === "drawn") {
      // the viewer draws its warm-up, hidden (above): its plots' first frame, before the run's data
      step = "preparing"; box.textContent = `${what}: preparing the plots…`;
    } else if (frames.firstDataAt === null && frames.answeredAt === null) { step = "connecting"; box.textContent = `${what}: connecting to the live stream…`; }
    else if (frames.firstDataAt === null) { step = "waiting"; box.textContent = `${what}: waiting for the run's data…`; }
    else if (!holdsSample()) { step = "receiving"; box.textContent = `${what}: data arriving, drawing the first plots…`; }
    else {
      // the frame that ingested the first sample draws it; the one after it is on screen
      step = "drawing";
      clearInterval(statusTimer);
      window.requestAnimationFrame(() => window.requestAnimationFrame(() => {
        box.style.display = "none";
        box.dataset.step = "shown";
      }));
    }
    box.dataset.step = step;
  }
  if (live) {
    // At once, not when the page is parsed: the viewer's own script (re_viewer.js) holds the parse
    // until it has loaded, and the line said nothing meanwhile (issue 31 bug 6, session 11).
    liveStatus();
    statusTimer = setInterval(liveStatus, 250);
  }

  // The live view is a display, not the data (logs/rerun_live.py, figures from /api/logs/rerun):
  // each plot shows its last seconds, each logged variable at most so many points per second
  // (each bucket's min and max: spikes stay visible). Every sample is in the run's log: the replay
  // below and the Runs page's downloads. Said on the page, beside the replay link.
  const liveNote = (info) => `Live view: the last ${info.live_span_s} s of each plot, at most `
    + `${info.live_points_per_s} points/s per signal (each interval's min and max kept). Every sample is `
    + "in the run's log: the replay below, or the Runs page's downloads.";

  // "Replay from start": a link in a corner (the viewer's canvas covers the page), to the live
  // run's first log file as .rrd (converted up to now: a run still logging gives what it has).
  async function offerReplay(run, info) {
    let a = document.getElementById("xrf-replay");
    try {
      const r = await fetch(`/api/logs/runs/${run}`, { credentials: "same-origin" });
      const files = r.ok ? (await r.json()).files : [];
      if (!files.length) { const box = document.getElementById("xrf-live-note"); if (box) box.remove(); return; }
      // a link of the viewer's own (it sends no cookie, and opens only a path ending in .rrd:
      // server/http/logs.py viewer_link)
      const segs = files[0].name.split("/").map(encodeURIComponent).join("/");
      const l = await fetch(`/api/logs/runs/${run}/viewer-link/${segs}`, { credentials: "same-origin" });
      if (!l.ok) return;
      const path = (await l.json()).path;
      if (!a) {
        const box = document.createElement("div");
        box.id = "xrf-live-note";
        Object.assign(box.style, { position: "fixed", right: "12px", bottom: "40px", zIndex: "2147483647",
          maxWidth: "300px", padding: "6px 10px", borderRadius: "6px", font: "12px system-ui, sans-serif",
          color: "#e5e7eb", background: "rgba(17,24,39,.9)" });
        const p = document.createElement("p");
        p.style.margin = "0 0 6px";
        p.id = "xrf-live-text";
        a = document.createElement("a");
        a.id = "xrf-replay";
        a.target = "_blank";
        a.rel = "noopener";
        Object.assign(a.style, { display: "inline-block", padding: "4px 10px", borderRadius: "6px", color: "#fff",
          background: "rgba(30,64,175,.95)", textDecoration: "none", font: "13px system-ui, sans-serif" });
        const toggle = document.createElement("button");
        toggle.id = "xrf-canvas-toggle";
        toggle.type = "button";
        Object.assign(toggle.style, { marginLeft: "8px", padding: "4px 8px", borderRadius: "6px", border: "0",
          font: "12px system-ui, sans-serif", cursor: "pointer" });
        toggle.addEventListener("click", () => {
          full = !full;
          try { localStorage.setItem(FULL_KEY, full ? "1" : "0"); } catch (e) { /* storage off: this tab only */ }
          sizeCanvas();
        });
        box.append(p, a, toggle);
        document.body.appendChild(box);
      }
      document.getElementById("xrf-live-text").textContent = liveNote(info);
      sizeCanvas();
      a.textContent = `Replay run ${run} from its start`;
      a.title = "The whole run so far, every sample: its log, opened here as .rrd in a new tab";
      a.href = "/rerun/?url=" + encodeURIComponent(location.origin + path);
    } catch (e) { /* the appliance restarts: the next poll tries again */ }
  }

  if (live) {
    let shown, offered;
    const follow = async () => {
      try {
        const r = await fetch("/api/logs/rerun", { credentials: "same-origin" });
        if (r.ok) {
          const info = await r.json();
          if (shown === undefined) shown = liveRun = info.live_run;
          else if (info.live_run != null && info.live_run !== shown) { location.reload(); return; }
          if (info.live_run != null) document.title = `rerun · live run ${info.live_run}` + (info.live_running ? "" : " (ended)");
          if (info.live_run != null && offered !== info.live_run) { offered = info.live_run; offerReplay(info.live_run, info); }
        }
      } catch (e) { /* the appliance restarts: try again */ }
      setTimeout(follow, FOLLOW_MS);
    };
    follow();
  } else {
    const m = url.match(/\/api\/logs\/runs\/(\d+)\//);
    if (m) document.title = `rerun · run ${m[1]}`;
  }
  // test hook; debugMuted(): console.debug lines muted so far (see above);
  // frames(): frames drawn, asked for by the viewer, and reads of the live stream with data (see above)
  // wasm: the viewer's module being compiled (its loader in index.html takes it, see above)
  window.xrfRerunTab = { stop, live, wasm, appStarted, consoleDebug, debugMuted: () => debugMuted, frames: () => ({ ...frames, held: held.size }) };
})();
