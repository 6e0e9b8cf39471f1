// A Foxglove WebSocket client we did not write: Foxglove's own protocol library
// (@foxglove/ws-protocol, the one the Foxglove app and Lichtblick's WebSocket player are built on),
// with protobufjs decoding each protobuf channel from the FileDescriptorSet the server advertises.
//
//   node client.mjs --url ws://127.0.0.1:8765 [--subprotocol foxglove.websocket.v1] [--seconds 120]
//
// Connects (retrying while the server is not up yet) offering the library's own subprotocol unless
// --subprotocol says otherwise, subscribes to every channel, decodes every message from its channel's
// advertised schema, and when the server closes (or --seconds pass) prints one JSON summary on
// stdout: per topic the messages, bytes, decode failures and log times going backwards; the server's
// time messages; what the scene and the plots held. test/ros/test_live_view_ros.py asserts on it.
import { createHash } from "node:crypto";

import wsProtocol from "@foxglove/ws-protocol"; // CommonJS: no named exports
import protobuf from "protobufjs";
import "protobufjs/ext/descriptor.js";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

function parseArgs(argv) {
  const args = { url: "ws://127.0.0.1:8765", subprotocol: FoxgloveClient.SUPPORTED_SUBPROTOCOL, seconds: 120 };
  for (let i = 0; i < argv.length; i += 2) {
    const key = argv[i].replace(/^--/, "");
    if (!(key in args) || argv[i + 1] === undefined) {
      throw new Error(`unknown or incomplete option ${argv[i]} (--url, --subprotocol, --seconds)`);
    }
    args[key] = key === "seconds" ? Number(argv[i + 1]) : argv[i + 1];
  }
  return args;
}

// ------------------------------------------------------------------ decoding from the advertised schema
function protobufDecoder(channel) {
  const root = protobuf.Root.fromDescriptor(Buffer.from(channel.schema, "base64"));
  const type = root.lookupType(channel.schemaName);
  return (bytes) => type.toObject(type.decode(bytes), { longs: Number, enums: String, bytes: Buffer, defaults: true });
}

// The JSON Schema subset the live view uses (object, number, integer, string, boolean): a value
// that the schema does not declare, or of another type, is a decode failure.
function checkJson(value, schema, path) {
  const type = schema.type;
  if (type === "object") {
    if (typeof value !== "object" || value === null || Array.isArray(value)) {
      throw new Error(`${path}: expected an object`);
    }
    const properties = schema.properties ?? {};
    for (const [key, item] of Object.entries(value)) {
      if (!(key in properties)) {
        throw new Error(`${path}.${key}: not in the schema`);
      }
      checkJson(item, properties[key], `${path}.${key}`);
    }
  } else if (type === "number" && typeof value !== "number") {
    throw new Error(`${path}: expected a number`);
  } else if (type === "integer" && !Number.isInteger(value)) {
    throw new Error(`${path}: expected an integer`);
  } else if (type === "string" && typeof value !== "string") {
    throw new Error(`${path}: expected a string`);
  } else if (type === "boolean" && typeof value !== "boolean") {
    throw new Error(`${path}: expected a boolean`);
  }
}

function jsonDecoder(channel) {
  if (channel.schemaEncoding !== "jsonschema") {
    throw new Error(`json channel ${channel.topic} has schema encoding ${channel.schemaEncoding}`);
  }
  const schema = JSON.parse(channel.schema);
  const text = new TextDecoder("utf-8", { fatal: true });
  return (bytes) => {
    const value = JSON.parse(text.decode(bytes));
    checkJson(value, schema, channel.topic);
    return value;
  };
}

function decoderOf(channel) {
  if (channel.encoding === "protobuf") {
    return protobufDecoder(channel);
  }
  if (channel.encoding === "json") {
    return jsonDecoder(channel);
  }
  throw new Error(`no decoder for encoding ${channel.encoding} (topic ${channel.topic})`);
}

// ------------------------------------------------------------------ what the channels held
function newTopic(channel) {
  return { encoding: channel.encoding, schemaName: channel.schemaName, schemaEncoding: channel.schemaEncoding,
           messages: 0, bytes: 0, decode_failures: 0, first_failure: null, log_time_backwards: 0,
           first_log_time_ns: null, last_log_time_ns: null, digests: {} };
}

const scene = { entity_ids: new Set(), frame_ids: new Set(), updates: 0 };
const plots = { paths: new Set(), time_first: null, time_last: null, range_true_first: null,
                range_true_last: null, time_backwards: 0 };
const raster = { encodings: new Set(), last_size: null, bad_data_length: 0 };

function leafPaths(value, prefix, into) {
  for (const [key, item] of Object.entries(value)) {
    if (typeof item === "object" && item !== null) {
      leafPaths(item, `${prefix}.${key}`, into);
    } else {
      into.add(`${prefix}.${key}`);
    }
  }
}

function look(topic, schemaName, message) {
  if (schemaName === "foxglove.SceneUpdate") {
    scene.updates += 1;
    for (const entity of message.entities) {
      scene.entity_ids.add(entity.id);
      scene.frame_ids.add(entity.frameId);
    }
  } else if (schemaName === "foxglove.RawImage") {
    raster.encodings.add(message.encoding);
    raster.last_size = [message.width, message.height];
    if (message.data.length !== message.step * message.height) {
      raster.bad_data_length += 1;
    }
  } else if (topic === "/plots") {
    leafPaths(message, topic, plots.paths);
    if (plots.time_last !== null && message.time < plots.time_last) {
      plots.time_backwards += 1;
    }
    plots.time_first ??= message.time;
    plots.time_last = message.time;
    if (message.range_true !== undefined) {
      plots.range_true_first ??= message.range_true;
      plots.range_true_last = message.range_true;
    }
  }
}

// ------------------------------------------------------------------ the connection
// The client is made with its socket, before the socket opens: the server speaks first (serverInfo,
// advertise), and a message that arrives before a listener is set is lost.
function connect(args, deadline, listen) {
  return new Promise((resolve, reject) => {
    const ws = new WebSocket(args.url, [args.subprotocol]);
    const client = new FoxgloveClient({ ws });
    listen(client);
    ws.once("open", () => resolve({ ws, client }));
    ws.once("error", (error) => {
      if (error.code === "ECONNREFUSED" && Date.now() < deadline) {
        setTimeout(() => connect(args, deadline, listen).then(resolve, reject), 100);
      } else {
        reject(error);
      }
    });
  });
}

async function main() {
  const args = parseArgs(process.argv.slice(2));
  const deadline = Date.now() + 1000 * args.seconds;
  const summary = { subprotocol_offered: args.subprotocol, subprotocol: null, server: null, errors: [],
                    topics: {}, time: { messages: 0, backwards: 0, first_ns: null, last_ns: null } };
  const channels = new Map(); // channel id -> {channel, decode}
  const subscriptions = new Map(); // subscription id -> channel id
  let lastTime = null;
  let opened = false;

  const listen = (client) => {
    client.on("serverInfo", (info) => {
      summary.server = { name: info.name, capabilities: info.capabilities };
    });
    client.on("error", (error) => {
      if (opened) {
        summary.errors.push(String(error.message ?? error));
      }
    });
    client.on("advertise", (advertised) => {
      for (const channel of advertised) {
        let decode;
        try {
          decode = decoderOf(channel);
        } catch (error) {
          summary.errors.push(`schema of ${channel.topic}: ${error.message}`);
          decode = () => {
            throw error;
          };
        }
        channels.set(channel.id, { channel, decode });
        summary.topics[channel.topic] = newTopic(channel);
        subscriptions.set(client.subscribe(channel.id), channel.id);
      }
    });
    client.on("time", ({ timestamp }) => {
      summary.time.messages += 1;
      if (lastTime !== null && timestamp < lastTime) {
        summary.time.backwards += 1;
      }
      summary.time.first_ns ??= String(timestamp);
      summary.time.last_ns = String(timestamp);
      lastTime = timestamp;
    });
    client.on("message", ({ subscriptionId, timestamp, data }) => {
      const { channel, decode } = channels.get(subscriptions.get(subscriptionId));
      const topic = summary.topics[channel.topic];
      const bytes = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
      topic.messages += 1;
      topic.bytes += bytes.length;
      if (topic.last_log_time_ns !== null && timestamp < BigInt(topic.last_log_time_ns)) {
        topic.log_time_backwards += 1;
      }
      topic.first_log_time_ns ??= String(timestamp);
      topic.last_log_time_ns = String(timestamp);
      topic.digests[String(timestamp)] = createHash("sha1").update(bytes).digest("hex").slice(0, 16);
      try {
        look(channel.topic, channel.schemaName, decode(bytes));
      } catch (error) {
        topic.decode_failures += 1;
        topic.first_failure ??= error.message;
      }
    });
  };

  let connection;
  try {
    connection = await connect(args, deadline, listen);
  } catch (error) {
    summary.errors.push(`connect: ${error.message}`);
    return summary;
  }
  opened = true;
  const { ws, client } = connection;
  summary.subprotocol = ws.protocol;
  await new Promise((resolve) => {
    const timer = setTimeout(() => {
      client.close();
      resolve();
    }, Math.max(0, deadline - Date.now()));
    client.on("close", () => {
      clearTimeout(timer);
      resolve();
    });
  });
  summary.scene = { updates: scene.updates, entity_ids: [...scene.entity_ids].sort(),
                    frame_ids: [...scene.frame_ids].sort() };
  summary.plots = { ...plots, paths: [...plots.paths].sort() };
  summary.raster = { ...raster, encodings: [...raster.encodings] };
  return summary;
}

main().then(
  (summary) => process.stdout.write(`${JSON.stringify(summary)}\n`),
  (error) => {
    process.stderr.write(`${error.stack ?? error}\n`);
    process.exit(1);
  },
);
