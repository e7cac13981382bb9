// An MES session against cellctl with node-opcua: browse Objects/Cell, Start a job with a user identity,
// follow Jobs/Live/Step by subscription and JobStateChangedEventType events until the job ends, read
// Jobs/Last/VerificationMean_um. Prints one JSON object on stdout, with the SHA-1 thumbprint of the client's
// application certificate (certificate_sha1).
//   node mes.mjs '{"url": ..., "mode": "None"|"SignAndEncrypt", "user": ..., "password": ..., "routine": ...,
//                  "parameters": "{}", "seed": 3, "pki": dir, "cert": client.pem, "key": client-key.pem,
//                  "serverCert": server-cert.der, "browseOnly": false}'
// Without cert and key, node-opcua makes its own self-signed certificate in pki/own/ (as an MES installed fresh
// does) and uses it again on the next run with the same pki folder. browseOnly: stop after the browse.
import crypto from "node:crypto";
import fs from "node:fs";
import {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, UserTokenType, AttributeIds, DataType, TimestampsToReturn,
  ClientMonitoredItem, constructEventFilter, makeBrowsePath, StatusCodes,
} from "node-opcua-client";
import { OPCUACertificateManager } from "node-opcua-certificate-manager";

const o = JSON.parse(process.argv[2]);
const out = { browse: [], steps: [], events: [] };
const secure = o.mode !== "None";
const certificateManager = new OPCUACertificateManager({ rootFolder: o.pki, automaticallyAcceptUnknownCertificate: false });
await certificateManager.initialize();
if (o.serverCert) await certificateManager.trustCertificate(fs.readFileSync(o.serverCert));  // pinned

const client = OPCUAClient.create({
  applicationName: "cellctl test MES", applicationUri: o.appUri || "urn:cellctl-test:mes",
  securityMode: MessageSecurityMode[o.mode], securityPolicy: secure ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None,
  endpointMustExist: false, connectionStrategy: { maxRetry: 0 }, clientCertificateManager: certificateManager,
  ...(o.cert ? { certificateFile: o.cert, privateKeyFile: o.key } : {}),
});
const timeout = setTimeout(() => { console.log(JSON.stringify({ ...out, error: "timeout" })); process.exit(3); }, (o.timeout_s || 120) * 1000);
try {
  await client.connect(o.url);
  const session = await client.createSession(o.user ? { type: UserTokenType.UserName, userName: o.user, password: o.password } : undefined);
  const ns = (await session.readNamespaceArray()).indexOf("urn:cellctl");
  const path = async (p) => {
    const r = await session.translateBrowsePath(makeBrowsePath("RootFolder", "/Objects/" + p.split("/").map((s) => `${ns}:${s}`).join("/")));
    if (r.statusCode !== StatusCodes.Good) throw new Error(`no node ${p}: ${r.statusCode.toString()}`);
    return r.targets[0].targetId;
  };
  const cell = await path("Cell");
  for (const ref of (await session.browse(cell)).references) out.browse.push(ref.browseName.name);
  out.name = (await session.read({ nodeId: await path("Cell/Identification/Name"), attributeId: AttributeIds.Value })).value.value;
  if (o.browseOnly) {
    await session.close();
    await client.disconnect();
    finish();
  }

  const subscription = await session.createSubscription2({ requestedPublishingInterval: 100, publishingEnabled: true,
    requestedMaxKeepAliveCount: 20, requestedLifetimeCount: 600, maxNotificationsPerPublish: 1000 });
  const step = ClientMonitoredItem.create(subscription, { nodeId: await path("Cell/Jobs/Live/Step"), attributeId: AttributeIds.Value },
    { samplingInterval: 50, discardOldest: true, queueSize: 100 }, TimestampsToReturn.Both);
  step.on("changed", (dv) => out.steps.push(dv.value.value));
  const live = [new Promise((r) => step.once("initialized", r))];
  const fields = ["EventType", "Severity", "Message", "JobId", "Routine", "State", "Reason"];
  const ended = new Promise((resolve) => {
    const events = ClientMonitoredItem.create(subscription, { nodeId: "i=2253", attributeId: AttributeIds.EventNotifier },
      { queueSize: 100, filter: constructEventFilter(fields) }, TimestampsToReturn.Both);
    live.push(new Promise((r) => events.once("initialized", r)));
    events.on("changed", (values) => {
      const e = Object.fromEntries(fields.map((f, i) => [f, values[i].value]));
      if (e.JobId === undefined || e.JobId === null) return;  // another event type
      const ev = { severity: e.Severity, message: e.Message?.text, job: e.JobId, routine: e.Routine, state: e.State, reason: e.Reason };
      out.events.push(ev);
      if (ev.job === out.job && ["done", "faulted", "aborted"].includes(ev.state)) resolve();
    });
  });
  await Promise.all(live);  // the monitored items are live before the job starts
  const call = await session.call({ objectId: await path("Cell/Jobs"), methodId: await path("Cell/Jobs/Start"), inputArguments: [
    { dataType: DataType.String, value: o.routine }, { dataType: DataType.String, value: o.parameters },
    { dataType: DataType.Int32, value: o.seed }] });
  out.start_status = call.statusCode.name;
  if (call.statusCode === StatusCodes.Good) {
    out.job = call.outputArguments[0].value;
    await ended;
    // Jobs/Last follows the end within a refresh: read until it names this job (bounded by the client's time-out)
    const lastId = await path("Cell/Jobs/Last/Id");
    while ((out.last_id = (await session.read({ nodeId: lastId, attributeId: AttributeIds.Value })).value.value) !== out.job) {
      await new Promise((r) => setTimeout(r, 100));
    }
    out.verification_mean_um = (await session.read({ nodeId: await path("Cell/Jobs/Last/VerificationMean_um"), attributeId: AttributeIds.Value })).value.value;
  }
  await subscription.terminate();
  await session.close();
  await client.disconnect();
} catch (err) {
  out.error = String(err && err.message || err);
}
finish();

function finish() {
  clearTimeout(timeout);
  try {
    out.certificate_sha1 = crypto.createHash("sha1").update(client.getCertificate()).digest("hex");
  } catch (err) {
    out.certificate_error = String(err && err.message || err);
  }
  console.log(JSON.stringify(out));
  process.exit(0);
}
