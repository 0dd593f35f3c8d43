// lightrig live page: status, frames, clock, link and journal of a running acquisition.
// API: docs/live-api.md. No dependencies, no build step.
'use strict';
(() => {
  const $ = (id) => document.getElementById(id);
  const token = new URLSearchParams(location.search).get('token') || '';
  const ENDED = new Set(['stopped', 'finished', 'failed']);
  const LINK_ERR = /^(retransmits|timeouts|bad_cobs|bad_crc|too_long|too_short|unknown_type|bad_payload|naks_.*|datagrams_dropped)$/;
  const MAX_LOG = 500, INIT_LOG = 200, MAX_CLOCK = 300;
  const st = {
    nextSeq: 0, ended: false, ws: null, wsLive: false, wsFails: 0, wsTimer: 0, polling: false,
    lastFrames: 0, lastStatus: 0, busy: {}, cams: new Map(), clock: [], linkCells: new Map(),
    logQueue: [], logTimer: 0,
  };

  // ---- helpers ---------------------------------------------------------------------------
  const isNum = (v) => typeof v === 'number' && Number.isFinite(v);
  const txt = (v, d = '—') => (v === null || v === undefined || v === '' ? d : String(v));
  const obj = (v) => (v && typeof v === 'object' && !Array.isArray(v) ? v : {});
  const css = (name) => getComputedStyle(document.documentElement).getPropertyValue(name).trim() || '#888';
  function set(id, v) { const e = $(id); if (e) e.textContent = v; return e || document.createElement('span'); }
  function num(v) { return !isNum(v) ? '—' : Number.isInteger(v) ? String(v) : String(+v.toPrecision(4)); }
  function fmtDur(s) {
    if (!isNum(s) || s < 0) return '—';
    s = Math.round(s);
    if (s < 60) return `${s} s`;
    if (s < 3600) return `${Math.floor(s / 60)} min ${String(s % 60).padStart(2, '0')} s`;
    return `${Math.floor(s / 3600)} h ${String(Math.floor((s % 3600) / 60)).padStart(2, '0')} min`;
  }
  function fmtTime(s) {
    if (!s) return '—';
    const d = new Date(s);
    return isNaN(d.getTime()) ? String(s) : d.toLocaleString();
  }
  function el(tag, cls, text) {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined) e.textContent = text;
    return e;
  }
  function withToken(url) {
    if (!token || !url) return url;
    return url + (url.includes('?') ? '&' : '?') + 'token=' + encodeURIComponent(token);
  }
  // A serde enum value in words: "PowerOn", {"Interlock": {"channel": 0}} -> "Interlock channel=0".
  const isEnum = (v) => v && typeof v === 'object' && !Array.isArray(v) && Object.keys(v).length === 1 && /^[A-Z]/.test(Object.keys(v)[0]);
  function en(v) {
    if (v === null || v === undefined) return '—';
    if (typeof v !== 'object') return String(v);
    if (Array.isArray(v)) return `[${v.map(en).join(', ')}]`;
    if (isEnum(v)) { const k = Object.keys(v)[0]; const inner = v[k]; return inner === null ? k : `${k} ${en(inner)}`; }
    return kv(v);
  }
  function kv(o) {
    return Object.entries(obj(o))
      .filter(([, x]) => x === null || typeof x !== 'object' || isEnum(x))
      .map(([k, x]) => `${k}=${en(x)}`).join(' ');
  }

  async function api(path, method = 'GET') {
    const res = await fetch(path, { method, headers: token ? { Authorization: 'Bearer ' + token } : {}, cache: 'no-store' });
    let body = null;
    try { body = await res.json(); } catch (_) { /* not JSON */ }
    if (!res.ok || (body && body.ok === false)) throw new Error((body && body.error) || `HTTP ${res.status} ${res.statusText}`);
    return body;
  }
  async function once(name, fn) {
    if (st.busy[name]) return;
    st.busy[name] = true;
    try { await fn(); } catch (e) { if (!st.ended && !st.wsLive) setConn(`${name}: ${e.message}`, 'bad'); } finally { st.busy[name] = false; }
  }
  function showMsg(text, err) { const m = set('message', text); m.classList.toggle('bad', !!err); }
  function setConn(text, cls) { const c = set('conn', text); c.className = 'conn ' + (cls || ''); }
  function prepCanvas(cv) {
    const w = cv.clientWidth, h = cv.clientHeight;
    if (!w || !h) return null;
    const dpr = window.devicePixelRatio || 1;
    const pw = Math.round(w * dpr), ph = Math.round(h * dpr);
    if (cv.width !== pw || cv.height !== ph) { cv.width = pw; cv.height = ph; }
    const ctx = cv.getContext('2d');
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    return [ctx, w, h];
  }

  // ---- status ------------------------------------------------------------------------------
  function setState(state) {
    const s = txt(state, 'unknown');
    set('state', s).className = 'badge st-' + s.replace(/[^a-z]/g, '');
  }
  function renderStatus(s) {
    if (!s || typeof s !== 'object') return;
    const run = obj(s.run);
    set('run-command', txt(run.command, 'live'));
    set('run-method', txt(run.method)); set('run-session', txt(run.session)); set('run-device', txt(run.device));
    set('run-started', fmtTime(run.started)).title = txt(run.started, '');
    set('run-pid', txt(run.pid)); set('run-watchers', txt(s.watchers));
    setState(s.state);
    set('reason', s.reason ? String(s.reason) : '');

    const step = s.step && typeof s.step === 'object' ? s.step : null;
    set('step-number', step ? `${txt(step.number, '?')}/${txt(step.of, '?')}` : '—');
    set('step-name', step ? txt(step.name, '') : '');
    set('step-attempt', step ? txt(step.attempt) : '—');
    set('step-triggered', step ? `${txt(step.triggered, 0)}/${txt(step.triggers, '?')}` : '—');
    set('step-frames', step ? txt(step.frames) : '—');

    const p = obj(s.progress);
    const trig = isNum(p.triggered) ? p.triggered : 0, tot = isNum(p.to_trigger) ? p.to_trigger : 0;
    set('progress', `${trig}/${tot}`);
    const pct = tot > 0 ? Math.min(100, (trig / tot) * 100) : 0;
    $('bar').style.width = pct + '%';
    set('pct', tot > 0 ? pct.toFixed(1) + ' %' : '');
    set('eta', (p.eta_is_bound === true && isNum(p.eta_s) ? '≥ ' : '') + fmtDur(p.eta_s));
    set('elapsed', fmtDur(p.elapsed_s));
    set('steps-done', `${txt(p.steps_done, 0)}/${txt(p.steps, '?')}`);
    set('frames-count', txt(p.frames, 0));
    set('missing', txt(p.missing, 0)).classList.toggle('bad', isNum(p.missing) && p.missing > 0);
    set('trigger-rate', `${isNum(p.trigger_rate_hz) ? p.trigger_rate_hz.toFixed(1) : '—'} triggers/s`);
    set('frame-rate', `${isNum(p.frame_rate_hz) ? p.frame_rate_hz.toFixed(1) : '—'} frames/s`);

    const d = obj(s.device);
    set('dev-state', txt(d.state)).className = 'badge small dev-' + txt(d.state, '').replace(/[^a-z]/g, '');
    set('dev-fault', d.fault ? en(d.fault) : 'none').classList.toggle('bad', !!d.fault);
    set('dev-boot', txt(d.boot_id));
    renderLasers(d.lasers_armed);
    renderStop(s.stop);
    renderLink(s.link);
    renderClock(s.clock);
    if (ENDED.has(s.state)) markEnded(s.state, s.reason);
  }
  function renderLasers(mask) {
    const box = $('lasers');
    const m = isNum(mask) ? mask >>> 0 : 0;
    const n = Math.max(3, m ? m.toString(2).length : 0);
    if (box.childElementCount !== n) {
      box.replaceChildren(...Array.from({ length: n }, (_, i) => { const e = el('span', 'led', String(i)); e.title = `laser ${i}`; return e; }));
    }
    [...box.children].forEach((e, i) => e.classList.toggle('on', ((m >>> i) & 1) === 1));
    set('lasers-mask', isNum(mask) ? `armed 0b${m.toString(2)}` : '');
  }
  function renderStop(stop) {
    const s = obj(stop);
    for (const k of ['requested', 'sent', 'answered']) $('stop-' + k).classList.toggle('on', !!s[k]);
  }
  function renderLink(link) {
    const box = $('link');
    for (const [k, v] of Object.entries(obj(link))) {
      let cell = st.linkCells.get(k);
      if (!cell) {
        cell = el('div', 'cnt');
        cell.append(el('span', '', k), el('b'));
        box.append(cell);
        st.linkCells.set(k, cell);
      }
      cell.lastChild.textContent = typeof v === 'object' ? en(v) : txt(v);
      cell.classList.toggle('bad', LINK_ERR.test(k) && isNum(v) && v > 0);
    }
  }
  function renderClock(c) {
    c = obj(c);
    set('clk-residual', isNum(c.residual_us) ? c.residual_us.toFixed(2) + ' µs' : '—');
    const ppm = isNum(c.rate) ? (c.rate - 1) * 1e6 : null;
    set('clk-rate', isNum(c.rate) ? `${c.rate.toFixed(7)} (${ppm >= 0 ? '+' : ''}${ppm.toFixed(2)} ppm)` : '—');
    set('clk-rtt', isNum(c.min_rtt_us) ? `${num(c.min_rtt_us)} µs` : '—');
    set('clk-samples', txt(c.samples));
    if (isNum(c.residual_us)) {
      st.clock.push([Date.now(), c.residual_us]);
      if (st.clock.length > MAX_CLOCK) st.clock.splice(0, st.clock.length - MAX_CLOCK);
      drawClock();
    }
  }
  function drawClock() {
    const pts = st.clock, p = prepCanvas($('clock-plot'));
    if (!p || !pts.length) return;
    const [ctx, w, h] = p, pad = 4, top = 14;
    let lo = 0, hi = 0;
    for (const [, v] of pts) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    if (hi - lo < 1e-9) hi = lo + 1;
    const t0 = pts[0][0], t1 = Math.max(pts[pts.length - 1][0], t0 + 1);
    const X = (t) => pad + ((t - t0) / (t1 - t0)) * (w - 2 * pad);
    const Y = (v) => h - pad - ((v - lo) / (hi - lo)) * (h - top - pad);
    ctx.strokeStyle = css('--line'); ctx.lineWidth = 1;
    ctx.beginPath(); ctx.moveTo(pad, Y(0)); ctx.lineTo(w - pad, Y(0)); ctx.stroke();
    ctx.strokeStyle = css('--accent'); ctx.lineWidth = 1.5; ctx.beginPath();
    pts.forEach(([t, v], i) => (i ? ctx.lineTo(X(t), Y(v)) : ctx.moveTo(X(t), Y(v))));
    ctx.stroke();
    ctx.fillStyle = css('--muted'); ctx.font = '10px system-ui, sans-serif';
    ctx.fillText(`${hi.toFixed(2)} µs`, pad, 10);
    const span = `${Math.round((t1 - t0) / 1000)} s`;
    ctx.fillText(span, w - pad - ctx.measureText(span).width, 10);
  }

  // ---- frames ------------------------------------------------------------------------------
  function camCard(c) {
    let cam = st.cams.get(c);
    if (cam) return cam;
    const card = el('section', 'card cam');
    const head = el('h2', '', `Camera ${c} `);
    const opt = el('label', 'opt'); const log = el('input'); log.type = 'checkbox'; log.checked = true;
    opt.append(log, ' log');
    head.append(opt);
    const wrap = el('div', 'imgwrap');
    const img = el('img'); img.id = `frame-${c}`; img.alt = `camera ${c}, latest frame`;
    const spot = el('div', 'spot'); spot.hidden = true;
    wrap.append(img, spot);
    const hist = el('canvas', 'hist');
    const axis = el('div', 'axis'); axis.append(el('span', '', '0'), el('span'));
    const facts = el('div', 'facts');
    card.append(head, wrap, hist, axis, facts);
    cam = { c, card, img, wrap, spot, hist, log, axis, facts, seq: undefined, f: null };
    log.addEventListener('change', () => drawHist(cam));
    const after = [...st.cams.values()].filter((x) => x.c > c).sort((a, b) => a.c - b.c)[0];
    $('frames').insertBefore(card, after ? after.card : null);
    st.cams.set(c, cam);
    $('no-frames').hidden = true;
    return cam;
  }
  function renderFrame(f) {
    if (!f || typeof f !== 'object' || !Number.isInteger(f.camera)) return;
    const cam = camCard(f.camera);
    if (cam.f && cam.seq === f.seq) return;
    cam.seq = f.seq; cam.f = f;
    if (f.thumbnail) { const u = withToken(f.thumbnail); if (cam.img.getAttribute('src') !== u) cam.img.src = u; }
    const w = f.width, h = f.height, dims = isNum(w) && isNum(h) && w > 0 && h > 0;
    if (dims) cam.wrap.style.aspectRatio = `${w} / ${h}`;
    const sp = f.spot && typeof f.spot === 'object' ? f.spot : null;
    const spotOk = dims && sp && isNum(sp.x) && isNum(sp.y);
    cam.spot.hidden = !spotOk;
    if (spotOk) { cam.spot.style.left = `${(sp.x / w) * 100}%`; cam.spot.style.top = `${(sp.y / h) * 100}%`; }
    const float = f.clipped === null || f.clipped === undefined;
    cam.axis.lastChild.textContent = isNum(f.bits) && !float && f.bits <= 32 ? String(2 ** f.bits - 1) : num(f.max);
    const t = f.trigger && typeof f.trigger === 'object' ? f.trigger : null;
    const clipped = el('span', isNum(f.clipped) && f.clipped > 0 ? 'bad' : '', float ? 'n/a (float)' : txt(f.clipped));
    const lines = [
      [`${txt(w, '?')}×${txt(h, '?')} · ${txt(f.bits, '?')} bit${f.channels > 1 ? ` · ${f.channels} ch` : ''}${f.ext ? ' · ' + f.ext : ''}`],
      [`min ${num(f.min)} · max ${num(f.max)} · clipped `, clipped],
      [`trigger tick ${t ? txt(t.tick) : '—'} · frame ${txt(f.frame)} · step ${txt(f.step)} · seq ${txt(f.seq)}`],
    ];
    if (spotOk) lines.push([`spot x ${sp.x.toFixed(1)}, y ${sp.y.toFixed(1)}`]);
    cam.facts.replaceChildren(...lines.map((parts) => { const d = el('div'); d.append(...parts); return d; }));
    drawHist(cam);
  }
  function drawHist(cam) {
    const f = cam.f, bins = f && Array.isArray(f.histogram) ? f.histogram : null;
    const p = bins && bins.length ? prepCanvas(cam.hist) : null;
    if (!p) return;
    const [ctx, w, h] = p, log = cam.log.checked;
    const val = (n) => (isNum(n) && n > 0 ? (log ? Math.log10(1 + n) : n) : 0);
    let peak = 0;
    for (const n of bins) peak = Math.max(peak, val(n));
    if (!peak) return;
    const bw = w / bins.length, accent = css('--accent'), bad = css('--bad');
    bins.forEach((n, i) => {
      const bh = (val(n) / peak) * (h - 2);
      if (bh <= 0) return;
      ctx.fillStyle = i === bins.length - 1 && f.clipped > 0 ? bad : accent;
      ctx.fillRect(i * bw, h - bh, Math.max(1, bw - 0.5), bh);
    });
  }

  // ---- journal -----------------------------------------------------------------------------
  function recType(r) {
    if (typeof r === 'string') return [r, {}];
    if (!r || typeof r !== 'object') return ['?', {}];
    if (typeof r.type === 'string') return [r.type, r];
    if (typeof r.kind === 'string') return [r.kind, r];
    const k = Object.keys(r);
    return k.length === 1 ? [k[0], obj(r[k[0]])] : ['?', r];
  }
  const sa = (b) => `step ${txt(b.step, '?')} attempt ${txt(b.attempt, '?')}`;
  function evSummary(b) {
    const ev = b.event;
    let kind = '?', e = {};
    if (typeof ev === 'string') kind = ev;
    else if (isEnum(ev)) { kind = Object.keys(ev)[0]; e = obj(ev[kind]); }
    else if (ev && typeof ev === 'object') { kind = ev.type || ev.kind || '?'; e = ev; }
    switch (kind) {
      case 'Trigger': return [`Trigger cam ${txt(e.camera)} frame ${txt(e.frame)} · sequence ${txt(e.sequence)} item ${txt(e.item)} · tick ${txt(e.tick)}`, 'noisy'];
      case 'Fault': return [`Fault ${en(e.cause)} · tick ${txt(e.tick)}`, 'bad'];
      case 'Underrun': return [`Underrun ${kv(e)}`, 'bad'];
      case 'State': return [`State ${en(e.state)} · armed 0b${isNum(e.armed) ? e.armed.toString(2) : '?'}`, ''];
      case 'Log': return [`Log ${en(e.level)}: ${txt(e.text, '')}`, e.level === 'Error' ? 'bad' : e.level === 'Warn' ? 'warn' : ''];
      case 'Buffer': case 'Exposure': return [`${kind} ${kv(e)}`, 'noisy'];
      default: return [`${kind} ${kv(e)}`.trim(), ''];
    }
  }
  function summarize(type, b) {
    switch (type) {
      case 'SessionStarted': return [`session ${txt(b.session_id)}`, 'ok'];
      case 'Resumed': return [`attempt ${txt(b.attempt)}${b.dropped_bytes ? ` · dropped ${b.dropped_bytes} B of damaged journal tail` : ''}`, b.dropped_bytes ? 'warn' : ''];
      case 'DeviceConnected': return [`boot ${txt(b.boot_id)} · reset ${en(b.reset_cause)}`, b.reset_cause === 'Watchdog' || b.reset_cause === 'Panic' ? 'warn' : ''];
      case 'FaultCleared': return [`${en(b.cause)} cleared (${txt(b.by)}) · boot ${txt(b.boot_id)}`, 'warn'];
      case 'StepStarted': return [`${sa(b)} · sequence ${txt(b.sequence_id)}`, 'step'];
      case 'StepPrepared': return [`${sa(b)} · ${txt(b.by)}: ${Array.isArray(b.actions) ? b.actions.join('; ') : ''}`, ''];
      case 'Event': return evSummary(b);
      case 'Frame': case 'FrameStored':
        return [`${sa(b)} cam ${txt(b.camera)} frame ${txt(b.frame)}${b.late ? ' (late)' : ''} · ${txt(b.file, '')}`, b.late ? 'warn' : 'noisy'];
      case 'FrameMissing': return [`${sa(b)} cam ${txt(b.camera)} frame ${txt(b.frame)} · ${txt(b.reason, '')}`, 'bad'];
      case 'FrameExtra': return [`${sa(b)} cam ${txt(b.camera)} frame ${txt(b.frame)} · ${en(b.reason)}`, 'warn'];
      case 'StepDone':
        return [`${sa(b)} done · ${txt(b.frames)}/${txt(b.triggers)} frames, ${txt(b.missing, 0)} missing, ${txt(b.extra, 0)} extra`, b.missing > 0 ? 'warn' : 'ok'];
      case 'StepAbandoned': return [`${sa(b)} abandoned · ${txt(b.reason, '')}`, 'bad'];
      case 'StepReopened': return [`${sa(b)} reopened · ${txt(b.reason, '')}`, 'warn'];
      case 'SessionDone': return ['every step done', 'ok'];
      default: return [kv(b), ''];
    }
  }
  function queueLog(seq, type, sum, cls) {
    st.logQueue.push({ seq, type, sum, cls });
    if (st.logQueue.length > MAX_LOG) st.logQueue.splice(0, st.logQueue.length - MAX_LOG);
    if (!st.logTimer) st.logTimer = setTimeout(flushLog, 150);
  }
  function flushLog() {
    st.logTimer = 0;
    const log = $('log');
    const stick = log.scrollTop + log.clientHeight >= log.scrollHeight - 24;
    const frag = document.createDocumentFragment();
    for (const it of st.logQueue) {
      const d = el('div', 'line ' + (it.cls || ''));
      d.append(el('span', 'seq', String(it.seq)), '  ', el('span', 'ty', it.type), '  ', it.sum);
      frag.append(d);
    }
    st.logQueue = [];
    log.append(frag);
    while (log.childElementCount > MAX_LOG) log.firstElementChild.remove();
    if (stick) log.scrollTop = log.scrollHeight;
  }
  function onRecord(seq, rec) {
    if (!Number.isInteger(seq) || seq < st.nextSeq) return;
    st.nextSeq = seq + 1;
    const [type, body] = recType(rec);
    let sum = '', cls = '';
    try { [sum, cls] = summarize(type, obj(body)); } catch (_) { sum = ''; }
    queueLog(seq, type, sum, cls);
  }
  function onJournal(j, initial) {
    const recs = Array.isArray(j && j.records) ? j.records : [];
    if (!initial && isNum(j.first) && j.first > st.nextSeq) queueLog('…', 'gap', `records ${st.nextSeq}–${j.first - 1} no longer kept`, 'warn');
    for (const r of recs) if (r) onRecord(r.seq, r.record);
    if (isNum(j.next)) st.nextSeq = Math.max(st.nextSeq, j.next);
  }
  async function loadJournal() {
    let since = 0, all = [], last = null;
    for (let i = 0; i < 8; i++) {
      const j = await api(`/api/v1/journal?since=${since}`);
      last = j || {};
      const recs = Array.isArray(last.records) ? last.records : [];
      all = all.concat(recs).slice(-INIT_LOG);
      if (!recs.length || !isNum(last.next)) break;
      since = recs[recs.length - 1].seq + 1;
      if (!isNum(since) || since >= last.next) break;
    }
    if (all.length && all[0].seq > 0) queueLog('…', '', `records before ${all[0].seq} not shown (the session's journal.jsonl has them all)`, 'noisy');
    onJournal({ records: all, next: last && last.next }, true);
  }

  // ---- connection --------------------------------------------------------------------------
  function onMessage(m) {
    if (!m || typeof m !== 'object') return;
    switch (m.type) {
      case 'hello': renderStatus(m.status); break;
      case 'status': renderStatus(m); break;
      case 'record': onRecord(m.seq, m.record); break;
      case 'frame': renderFrame(m); break;
      case 'lagged':
        queueLog('…', 'lagged', `fell behind: ${txt(m.skipped, '?')} records skipped`, 'warn');
        if (isNum(m.next)) st.nextSeq = m.next;
        break;
      case 'end': markEnded(m.state, m.reason); break;
      default: break;
    }
  }
  function connectWs() {
    if (st.ended) return;
    const proto = location.protocol === 'https:' ? 'wss:' : 'ws:';
    const url = `${proto}//${location.host}/api/v1/ws?since=${st.nextSeq}` + (token ? `&token=${encodeURIComponent(token)}` : '');
    let ws;
    try { ws = new WebSocket(url); } catch (_) { wsDown(); return; }
    st.ws = ws;
    ws.onopen = () => { st.wsLive = true; st.wsFails = 0; st.polling = false; setConn('live', 'ok'); };
    ws.onmessage = (ev) => { let m; try { m = JSON.parse(ev.data); } catch (_) { return; } onMessage(m); };
    ws.onerror = () => {};
    ws.onclose = () => { if (st.ws === ws) { st.ws = null; st.wsLive = false; wsDown(); } };
  }
  function wsDown() {
    if (st.ended) return;
    st.wsFails++;
    if (st.wsFails >= 2) st.polling = true;
    const delay = Math.min(30000, 1000 * 2 ** Math.min(st.wsFails - 1, 5));
    setConn(`${st.polling ? 'polling · ' : ''}reconnecting in ${Math.round(delay / 1000)} s`, 'warn');
    clearTimeout(st.wsTimer);
    st.wsTimer = setTimeout(connectWs, delay);
  }
  const pollStatus = () => once('status', async () => { st.lastStatus = Date.now(); renderStatus(await api('/api/v1/status')); });
  const pollJournal = () => once('journal', async () => onJournal(await api(`/api/v1/journal?since=${st.nextSeq}`), false));
  const pollFrames = () => once('frames', async () => {
    st.lastFrames = Date.now();
    const a = await api('/api/v1/frames');
    for (const f of Array.isArray(a && a.cameras) ? a.cameras : []) renderFrame(f);
  });
  function tick() {
    if (st.ended) return;
    const now = Date.now();
    if (now - st.lastFrames >= (st.polling ? 2000 : 5000)) pollFrames();
    if (st.polling && now - st.lastStatus >= 2000) { pollStatus(); pollJournal(); }
  }
  function markEnded(state, reason) {
    if (typeof state === 'string') setState(state);
    if (reason) set('reason', String(reason));
    const words = {
      finished: 'Run finished: every step done.',
      stopped: 'Run stopped. The device stays emergency-stopped until a person clears it (lightrig resume asks).',
      failed: 'Run failed.',
    };
    const b = $('banner');
    const why = reason && reason !== 'emergency stop' ? ` ${reason}` : '';
    b.textContent = (words[state] || `Run ended (${txt(state, 'unknown')}).`) + why;
    b.className = 'banner ' + txt(state, 'ended');
    b.hidden = false;
    if (st.ended) return;
    st.ended = true; st.polling = false;
    clearTimeout(st.wsTimer);
    for (const id of ['pause', 'resume', 'stop']) $(id).disabled = true;
    setConn('ended', '');
  }

  // ---- commands ----------------------------------------------------------------------------
  async function command(name) {
    if (name === 'stop' && !window.confirm('Emergency stop: turn the lasers off and end the run?')) return;
    showMsg(`${name}: sending…`);
    try {
      const a = obj(await api('/api/v1/' + name, 'POST'));
      if (a.stop) renderStop(a.stop);
      showMsg(a.message || `${name}: ${txt(a.state, 'ok')}`);
      if (typeof a.state === 'string' && !st.ended) setState(a.state);
    } catch (e) {
      showMsg(`${name}: ${e.message}`, true);
    }
    if (!st.ended && !st.wsLive) pollStatus();
  }

  // ---- start -------------------------------------------------------------------------------
  async function start() {
    for (const id of ['pause', 'resume', 'stop']) $(id).addEventListener('click', () => command(id));
    $('log-quiet').addEventListener('change', (e) => $('log').classList.toggle('quiet', e.target.checked));
    let rt = 0;
    window.addEventListener('resize', () => {
      clearTimeout(rt);
      rt = setTimeout(() => { drawClock(); st.cams.forEach(drawHist); }, 150);
    });
    try { st.lastStatus = Date.now(); renderStatus(await api('/api/v1/status')); } catch (e) { showMsg(`status: ${e.message}`, true); }
    pollFrames();
    try { await loadJournal(); } catch (e) { showMsg(`journal: ${e.message}`, true); }
    if (!st.ended) connectWs();
    setInterval(tick, 1000);
  }
  start();
})();
