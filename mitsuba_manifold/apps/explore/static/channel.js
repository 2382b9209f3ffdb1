// The tab's websocket to the explorer (mitsuba_manifold/apps/explore/web/session.py).
// Every request carries a sequence number; the server answers the newest request of each
// kind and repeats its seq (and the point x) in the answer. Answers of a kind are applied in
// order only: one arriving after a newer answer of its kind is late and dropped.
"use strict";

// This page's id: the server ends the renders this page started when its websocket closes.
const TAB = (window.crypto && crypto.randomUUID) ? crypto.randomUUID() : "t" + Math.random().toString(36).slice(2);

class Channel {
  constructor(onMessage, onOpen) {
    this.onMessage = onMessage;
    this.onOpen = onOpen;
    this.seq = 0;
    this.latest = {};     // kind -> seq of the newest request
    this.answered = {};   // kind -> seq of the newest answer applied
    this.sentAt = {};     // seq -> time sent
    this.dropped = 0;     // late answers dropped
    this.queued = null;   // messages waiting for the socket
    this.owed = 0;        // kinds the page has still to ask for the point shown (a drag resting)
    this.connect();
  }
  connect() {
    const proto = location.protocol === "https:" ? "wss" : "ws";
    this.ws = new WebSocket(`${proto}://${location.host}/ws?tab=${TAB}`);
    this.ws.binaryType = "arraybuffer";
    this.ws.onopen = () => {
      setStatus("connected");   // a first warning stays (state.errors) until its source answers
      clearError("connection");
      update({ connected: true });
      const queued = this.queued || [];
      this.queued = null;
      for (const m of queued) this.ws.send(m);
      if (this.opened && this.onOpen) this.onOpen();   // reconnected: the page's whole state asked again
      this.opened = true;
    };
    this.ws.onclose = (ev) => {
      update({ connected: false });   // what the server showed is dimmed where it is not the point's
      setStatus(`disconnected from the server${ev.reason ? " (" + ev.reason + ")" : ""} — retrying…`, true, "connection");
      setTimeout(() => this.connect(), 1000);
    };
    this.ws.onmessage = (ev) => this.receive(ev.data);
  }
  // Send one message standing for a request of each kind in `kinds`; returns its seq.
  send(body, kinds) {
    const seq = ++this.seq;
    for (const k of kinds) this.latest[k] = seq;
    this.sentAt[seq] = performance.now();
    const text = JSON.stringify(Object.assign({ seq }, body));
    if (this.ws.readyState === WebSocket.OPEN) this.ws.send(text);
    else (this.queued = this.queued || []).push(text);
    return seq;
  }
  receive(data) {
    const view = new DataView(data);
    const n = view.getUint32(0, true);
    const meta = JSON.parse(new TextDecoder().decode(new Uint8Array(data, 4, n)));
    const payload = data.slice(4 + n);
    const kind = meta.type === "error" ? meta.kind : meta.type;
    if (kind && meta.seq != null) {
      if (meta.seq <= (this.answered[kind] || 0)) { this.dropped++; return; }   // late: a newer one is shown
      this.answered[kind] = meta.seq;
      if (this.sentAt[meta.seq] !== undefined) meta.round_trip_ms = performance.now() - this.sentAt[meta.seq];
    }
    for (const s in this.sentAt) if (+s < this.oldestWanted()) delete this.sentAt[s];
    this.onMessage(meta, payload);
  }
  oldestWanted() { return Math.min(...Object.keys(this.latest).map((k) => this.latest[k]), this.seq); }
  // Kinds whose newest request is not answered yet.
  pending() { return this.owed + Object.keys(this.latest).filter((k) => (this.answered[k] || 0) < this.latest[k]).length; }
  isCurrent(kind, seq) { return this.latest[kind] === seq; }
}
