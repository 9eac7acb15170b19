// The dashboard: recent inspections from GET /v1/inspections (its filters, its cursor), and a form
// that uploads a bundle with POST /v1/inspections and follows it with the long poll until it ends.
(function () {
  'use strict';
  var rows = document.querySelector('#inspections tbody');
  var more = document.getElementById('more');
  var listStatus = document.getElementById('list-status');
  var filters = document.getElementById('filters');
  var cursor = null;
  var refresh = null;

  function text(tag, value, cls) {
    var el = document.createElement(tag);
    el.textContent = value == null ? '–' : String(value);
    if (cls) el.className = cls;
    return el;
  }

  function query() {
    var params = new URLSearchParams();
    new FormData(filters).forEach(function (value, key) { if (value) params.set(key, value); });
    params.set('limit', '50');
    return params;
  }

  function problemText(body, status) {
    try {
      var p = JSON.parse(body);
      return (p.title || ('HTTP ' + status)) + (p.detail ? ': ' + p.detail : '');
    } catch (e) {
      return 'HTTP ' + status;
    }
  }

  function row(item) {
    var tr = document.createElement('tr');
    tr.dataset.id = item.id;
    tr.appendChild(text('td', new Date(item.created_at).toLocaleString()));
    var status = item.status;
    if (item.progress && item.status === 'running') {
      status += ' (' + item.progress.stage + ' ' + Math.round(100 * (item.progress.fraction || 0)) + '%)';
    }
    tr.appendChild(text('td', status, item.status));
    tr.appendChild(text('td', item.verdict, item.verdict));
    tr.appendChild(text('td', item.decision && item.decision.replace(/_/g, ' '), item.decision));
    tr.appendChild(text('td', item.review_required == null ? null : (item.review_required ? 'required' : 'no'),
      item.review_required ? 'review' : ''));
    tr.appendChild(text('td', item.serial));
    tr.appendChild(text('td', item.connection));
    tr.appendChild(text('td', item.client_reference));
    var station = document.createElement('td');
    if (item.station) {
      var link = document.createElement('a');
      link.href = '/v1/stations/' + encodeURIComponent(item.station) + '?format=html';
      link.textContent = item.station;
      station.appendChild(link);
    }
    tr.appendChild(station);
    var cell = document.createElement('td');
    if (item.status === 'succeeded') {
      var a = document.createElement('a');
      a.href = '/v1/inspections/' + encodeURIComponent(item.id) + '/report?format=html';
      a.textContent = 'report';
      cell.appendChild(a);
    } else {
      cell.textContent = '–';
    }
    tr.appendChild(cell);
    return tr;
  }

  function load(append) {
    var params = query();
    if (append && cursor) params.set('cursor', cursor);
    listStatus.textContent = 'Loading…';
    return fetch('/v1/inspections?' + params.toString(), { headers: { Accept: 'application/json' } })
      .then(function (r) {
        return r.text().then(function (body) {
          if (!r.ok) throw new Error(problemText(body, r.status));
          return JSON.parse(body);
        });
      })
      .then(function (page) {
        if (!append) rows.textContent = '';
        page.items.forEach(function (item) { rows.appendChild(row(item)); });
        cursor = page.next_cursor || null;
        more.hidden = !cursor;
        listStatus.textContent = rows.children.length ? '' : 'No inspection matches.';
        document.body.dataset.listed = String(rows.children.length);
        // Follow unfinished work while it runs.
        var busy = page.items.some(function (i) { return i.status === 'queued' || i.status === 'running'; });
        clearTimeout(refresh);
        if (busy && !append) refresh = setTimeout(function () { load(false); }, 3000);
      })
      .catch(function (e) { listStatus.textContent = e.message; listStatus.className = 'error'; });
  }

  filters.addEventListener('submit', function (e) { e.preventDefault(); load(false); });
  more.addEventListener('click', function () { load(true); });

  // Submission.
  var form = document.getElementById('submit-form');
  var drop = document.getElementById('drop');
  var input = document.getElementById('bundle-file');
  var button = document.getElementById('submit-button');
  var bar = document.getElementById('upload-progress');
  var status = document.getElementById('submit-status');
  var chosen = null;

  function choose(file) {
    chosen = file || null;
    button.disabled = !chosen;
    status.className = '';
    status.textContent = chosen ? chosen.name + ' (' + Math.round(chosen.size / 1024) + ' KiB)' : '';
  }
  input.addEventListener('change', function () { choose(input.files[0]); });
  ['dragenter', 'dragover'].forEach(function (t) {
    drop.addEventListener(t, function (e) { e.preventDefault(); drop.classList.add('over'); });
  });
  ['dragleave', 'drop'].forEach(function (t) {
    drop.addEventListener(t, function (e) { e.preventDefault(); drop.classList.remove('over'); });
  });
  drop.addEventListener('drop', function (e) { choose(e.dataTransfer.files[0]); });

  // The report's review reasons in the order its page lists them (quality, then the decision's).
  function firstReason(report) {
    var quality = ((report.quality && report.quality.reasons) || []).map(function (q) { return q.message; });
    var decision = (report.decision_finding && report.decision_finding.reasons) || [];
    var first = quality.concat(decision)[0];
    if (!first) return null;
    var end = first.indexOf('. ');
    return end > 0 ? first.slice(0, end + 1) : first;
  }

  function follow(id) {
    fetch('/v1/inspections/' + encodeURIComponent(id) + '?wait=30s', { headers: { Accept: 'application/json' } })
      .then(function (r) { return r.json(); })
      .then(function (item) {
        if (item.status === 'queued' || item.status === 'running') {
          var p = item.progress;
          status.textContent = item.status + (p ? ': ' + p.stage + ' ' + Math.round(100 * (p.fraction || 0)) + '%' : '');
          bar.removeAttribute('value');
          follow(id);
          return;
        }
        bar.hidden = true;
        status.textContent = '';
        status.appendChild(document.createTextNode(item.status + (item.verdict ? ': ' + item.verdict : '') +
          (item.decision ? ', decision ' + item.decision.replace(/_/g, ' ') : '') +
          (item.review_required ? ', review required' : '') + ' '));
        if (item.status === 'succeeded') {
          var a = document.createElement('a');
          a.href = '/v1/inspections/' + encodeURIComponent(id) + '/report?format=html';
          a.textContent = 'open the report';
          status.appendChild(a);
          // The first reason for review, its opening sentence: what a quality engineer reads first.
          fetch('/v1/inspections/' + encodeURIComponent(id) + '/report', { headers: { Accept: 'application/json' } })
            .then(function (r) { return r.ok ? r.json() : null; })
            .then(function (report) {
              var reason = report && firstReason(report);
              if (reason) {
                var why = document.createElement('span');
                why.className = 'why';
                why.textContent = ' Why review: ' + reason;
                status.appendChild(why);
              }
            });
        } else if (item.error) {
          status.appendChild(document.createTextNode(item.error.detail || item.error.title || ''));
        }
        load(false);
      })
      .catch(function (e) { status.textContent = e.message; status.className = 'error'; });
  }

  form.addEventListener('submit', function (e) {
    e.preventDefault();
    if (!chosen) return;
    var reference = document.getElementById('client-reference').value.trim();
    var rule = document.getElementById('arc-rule').value;
    var pipelineText = document.getElementById('pipeline-options').value.trim();
    var pipeline = null;
    if (pipelineText) {
      try {
        pipeline = JSON.parse(pipelineText);
      } catch (err) {
        status.className = 'error';
        status.textContent = 'Pipeline options: not JSON (' + err.message + ')';
        return;
      }
    }
    var xhr = new XMLHttpRequest();
    var body;
    if (pipeline) {
      // Pipeline options travel only in a multipart `options` part, with the bundle beside it.
      var options = { pipeline: pipeline };
      if (reference) options.client_reference = reference;
      if (rule) options.arc_rule = rule;
      body = new FormData();
      body.append('options', new Blob([JSON.stringify(options)], { type: 'application/json' }));
      body.append('bundle', chosen, chosen.name);
      xhr.open('POST', '/v1/inspections');
    } else {
      var params = new URLSearchParams();
      if (reference) params.set('client_reference', reference);
      if (rule) params.set('arc_rule', rule);
      xhr.open('POST', '/v1/inspections' + (params.toString() ? '?' + params.toString() : ''));
      var name = chosen.name.toLowerCase();
      xhr.setRequestHeader('Content-Type', name.endsWith('.zip') ? 'application/zip' :
        name.endsWith('.tar') ? 'application/x-tar' : 'application/octet-stream');
      body = chosen;
    }
    xhr.setRequestHeader('Accept', 'application/json');
    bar.hidden = false;
    bar.value = 0;
    button.disabled = true;
    status.className = '';
    status.textContent = 'Uploading…';
    xhr.upload.onprogress = function (ev) {
      if (ev.lengthComputable) {
        bar.value = ev.loaded / ev.total;
        status.textContent = 'Uploading: ' + Math.round(100 * ev.loaded / ev.total) + '%';
      }
    };
    xhr.onerror = function () { bar.hidden = true; button.disabled = false; status.className = 'error'; status.textContent = 'The upload failed: the service could not be reached.'; };
    xhr.onload = function () {
      button.disabled = false;
      if (xhr.status !== 202) {
        bar.hidden = true;
        status.className = 'error';
        status.textContent = problemText(xhr.responseText, xhr.status);
        return;
      }
      var created = JSON.parse(xhr.responseText);
      status.textContent = 'Queued.';
      load(false);
      follow(created.id);
    };
    xhr.send(body);
  });

  load(false);
  // `/#inspection=ID` follows that inspection to its end, as after an upload from this page.
  var followed = /^#inspection=([0-9a-fA-F-]{36})$/.exec(location.hash);
  if (followed) {
    status.textContent = 'Following ' + followed[1] + '…';
    follow(followed[1]);
  }
})();
