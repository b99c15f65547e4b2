// fastdds_peer: a Fast DDS participant that talks to our nodes the way a ROS 2 node on
// rmw_fastrtps would at the DDS level, carrying opaque XCDR1 payloads (encapsulation header
// included), so it needs no generated types: the DDS type name is given on the command line.
//
//   fastdds_peer --domain N --duration S --out DIR [actions...]
//   --sub TOPIC TYPE QOS          take every sample; write DIR/sub<k>_<n>.bin, log "sample k n bytes writer-guid"
//   --pub TOPIC TYPE QOS FILE N   after a match, write FILE's bytes N times (10 ms apart)
//   --call RQTOPIC RQTYPE RRTOPIC RRTYPE FILE N
//                                  N times: send FILE's request bytes (rmw_cyclonedds header inside),
//                                  wait for the reply whose header matches, log "reply k i microseconds"
//                                  (k: the --call's index); the first reply goes to DIR/reply<k>.bin
//   QOS: reliable | best_effort | reliable_transient (transient local, keep-last 100)
// Discovery is logged too: "participant GUIDPREFIX userdata TEXT", "writer GUID TOPIC TYPE userdata TEXT",
// "reader GUID TOPIC TYPE userdata TEXT". With PEER_TIMESTAMPS set, every line ends in " t=<CLOCK_MONOTONIC ns>". Unicast discovery on 127.0.0.1 only (participant ids 0..29).
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/log/Log.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/domain/DomainParticipantListener.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/DataWriterListener.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/DataReaderListener.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/TopicDataType.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>
#include <fastdds/rtps/transport/UDPv4TransportDescriptor.h>
#include <fastrtps/utils/IPLocator.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <fstream>
#include <iterator>
#include <memory>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

using namespace eprosima::fastdds::dds;
using eprosima::fastrtps::rtps::GUID_t;
using eprosima::fastrtps::rtps::SerializedPayload_t;
using Bytes = std::vector<unsigned char>;

static std::mutex g_out;
static const bool g_stamp = std::getenv("PEER_TIMESTAMPS") != nullptr;
static void out(const std::string& text) {
  std::string line = text;
  if (g_stamp) {  // CLOCK_MONOTONIC ns: the same clock as Python's time.monotonic_ns() on Linux
    timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    line += " t=" + std::to_string(int64_t(ts.tv_sec) * 1000000000 + ts.tv_nsec);
  }
  std::lock_guard<std::mutex> lk(g_out);
  std::fwrite(line.data(), 1, line.size(), stdout);
  std::fputc('\n', stdout);
  std::fflush(stdout);
}

static std::string hex(const unsigned char* p, size_t n) {
  static const char* d = "0123456789abcdef";
  std::string s;
  for (size_t i = 0; i < n; ++i) { s += d[p[i] >> 4]; s += d[p[i] & 15]; }
  return s;
}
static std::string guid_hex(const GUID_t& g) {
  unsigned char b[16];
  std::memcpy(b, g.guidPrefix.value, 12);
  std::memcpy(b + 12, g.entityId.value, 4);
  return hex(b, 16);
}
static std::string printable(const std::vector<unsigned char>& v) {
  std::string s;
  for (unsigned char c : v) s += (c >= 32 && c < 127) ? char(c) : '.';
  return s;
}

// Opaque payload type: the sample is the serialized payload, encapsulation header included.
class RawType : public TopicDataType {
 public:
  explicit RawType(const std::string& name) {
    setName(name.c_str());
    m_typeSize = 1 << 16;  // a hint only: endpoints use dynamic payload memory
    m_isGetKeyDefined = false;
  }
  bool serialize(void* data, SerializedPayload_t* payload) override {
    auto* v = static_cast<Bytes*>(data);
    if (v->size() > payload->max_size) payload->reserve(static_cast<uint32_t>(v->size()));
    std::memcpy(payload->data, v->data(), v->size());
    payload->length = static_cast<uint32_t>(v->size());
    payload->encapsulation = (v->size() > 1 && (*v)[1] == 1) ? CDR_LE : CDR_BE;
    return true;
  }
  bool deserialize(SerializedPayload_t* payload, void* data) override {
    auto* v = static_cast<Bytes*>(data);
    v->assign(payload->data, payload->data + payload->length);
    return true;
  }
  std::function<uint32_t()> getSerializedSizeProvider(void* data) override {
    auto n = static_cast<uint32_t>(static_cast<Bytes*>(data)->size());
    return [n]() { return n; };
  }
  void* createData() override { return new Bytes(); }
  void deleteData(void* data) override { delete static_cast<Bytes*>(data); }
  bool getKey(void*, eprosima::fastrtps::rtps::InstanceHandle_t*, bool) override { return false; }
};

class PartListener : public DomainParticipantListener {
 public:
  void on_participant_discovery(DomainParticipant*, eprosima::fastrtps::rtps::ParticipantDiscoveryInfo&& info) override {
    if (info.status != eprosima::fastrtps::rtps::ParticipantDiscoveryInfo::DISCOVERED_PARTICIPANT) return;
    out("participant " + hex(info.info.m_guid.guidPrefix.value, 12) + " userdata " +
        printable(info.info.m_userData.data_vec()));
  }
  void on_publisher_discovery(DomainParticipant*, eprosima::fastrtps::rtps::WriterDiscoveryInfo&& info) override {
    if (info.status != eprosima::fastrtps::rtps::WriterDiscoveryInfo::DISCOVERED_WRITER) return;
    out("writer " + guid_hex(info.info.guid()) + " " + std::string(info.info.topicName().c_str()) + " " +
        std::string(info.info.typeName().c_str()) + " userdata " + printable(info.info.m_qos.m_userData.data_vec()));
  }
  void on_subscriber_discovery(DomainParticipant*, eprosima::fastrtps::rtps::ReaderDiscoveryInfo&& info) override {
    if (info.status != eprosima::fastrtps::rtps::ReaderDiscoveryInfo::DISCOVERED_READER) return;
    out("reader " + guid_hex(info.info.guid()) + " " + std::string(info.info.topicName().c_str()) + " " +
        std::string(info.info.typeName().c_str()) + " userdata " + printable(info.info.m_qos.m_userData.data_vec()));
  }
};

class SubListener : public DataReaderListener {
 public:
  SubListener(int k, std::string dir) : k_(k), dir_(std::move(dir)) {}
  void on_data_available(DataReader* r) override {
    Bytes v;
    SampleInfo info;
    while (r->take_next_sample(&v, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data) continue;
      int n = n_++;
      std::ofstream f(dir_ + "/sub" + std::to_string(k_) + "_" + std::to_string(n) + ".bin", std::ios::binary);
      f.write(reinterpret_cast<const char*>(v.data()), static_cast<std::streamsize>(v.size()));
      f.close();
      GUID_t g = eprosima::fastrtps::rtps::iHandle2GUID(info.publication_handle);
      out("sample " + std::to_string(k_) + " " + std::to_string(n) + " " + std::to_string(v.size()) + " " + guid_hex(g));
    }
  }
  void on_subscription_matched(DataReader*, const SubscriptionMatchedStatus& s) override {
    out("sub_matched " + std::to_string(k_) + " " + std::to_string(s.current_count));
  }
  void on_sample_rejected(DataReader*, const SampleRejectedStatus& s) override {
    out("sample_rejected " + std::to_string(k_) + " " + std::to_string(s.total_count));
  }
  void on_sample_lost(DataReader*, const SampleLostStatus& s) override {
    out("sample_lost " + std::to_string(k_) + " " + std::to_string(s.total_count));
  }
  void on_requested_incompatible_qos(DataReader*, const RequestedIncompatibleQosStatus& s) override {
    out("incompatible_qos " + std::to_string(k_) + " policy " + std::to_string(s.last_policy_id));
  }

 private:
  int k_;
  std::string dir_;
  std::atomic<int> n_{0};
};

class PubListener : public DataWriterListener {
 public:
  std::atomic<int> matched{0};
  void on_publication_matched(DataWriter*, const PublicationMatchedStatus& s) override { matched = s.current_count; }
};

struct Reply : public DataReaderListener {
  std::mutex m;
  std::vector<Bytes> got;
  void on_data_available(DataReader* r) override {
    Bytes v;
    SampleInfo info;
    while (r->take_next_sample(&v, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data) continue;
      std::lock_guard<std::mutex> lk(m);
      got.push_back(v);
    }
  }
  std::atomic<int> matched{0};
  void on_subscription_matched(DataReader*, const SubscriptionMatchedStatus& s) override { matched = s.current_count; }
};

static Bytes read_file(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return Bytes(std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>());
}

static void apply_qos(const std::string& q, ReliabilityQosPolicy& rel, DurabilityQosPolicy& dur, HistoryQosPolicy& hist) {
  rel.kind = (q == "best_effort") ? BEST_EFFORT_RELIABILITY_QOS : RELIABLE_RELIABILITY_QOS;
  dur.kind = (q == "reliable_transient") ? TRANSIENT_LOCAL_DURABILITY_QOS : VOLATILE_DURABILITY_QOS;
  hist.kind = KEEP_LAST_HISTORY_QOS;
  hist.depth = 100;
}

int main(int argc, char** argv) {
  int domain = 0;
  double duration = 5.0;
  std::string dir = ".";
  std::vector<std::vector<std::string>> subs, pubs, calls;
  for (int i = 1; i < argc; ++i) {
    std::string a = argv[i];
    auto take = [&](int n) {
      std::vector<std::string> v;
      for (int j = 0; j < n; ++j) {
        if (i + 1 >= argc) { std::fprintf(stderr, "fastdds_peer: %s needs %d arguments\n", a.c_str(), n); std::exit(2); }
        v.push_back(argv[++i]);
      }
      return v;
    };
    if (a == "--domain") domain = std::stoi(take(1)[0]);
    else if (a == "--duration") duration = std::stod(take(1)[0]);
    else if (a == "--out") dir = take(1)[0];
    else if (a == "--sub") subs.push_back(take(3));
    else if (a == "--pub") pubs.push_back(take(5));
    else if (a == "--call") calls.push_back(take(6));
    else { std::fprintf(stderr, "fastdds_peer: unknown argument %s\n", a.c_str()); return 2; }
  }

  if (std::getenv("PEER_VERBOSE")) Log::SetVerbosity(Log::Kind::Info);
  DomainParticipantQos pq;
  pq.name("fastdds_peer");
  if (!std::getenv("PEER_BUILTIN_TRANSPORTS")) {
    pq.transport().use_builtin_transports = false;
    auto udp = std::make_shared<eprosima::fastdds::rtps::UDPv4TransportDescriptor>();
    udp->interfaceWhiteList.emplace_back("127.0.0.1");
    pq.transport().user_transports.push_back(udp);
  }
  // announce often: a participant that starts after this one learns of it from these announcements
  pq.wire_protocol().builtin.discovery_config.leaseDuration_announcementperiod =
      eprosima::fastrtps::Duration_t(0, 250000000);
  auto& peers = pq.wire_protocol().builtin.initialPeersList;
  for (int pid = 0; pid < 30; ++pid) {
    eprosima::fastrtps::rtps::Locator_t loc;
    eprosima::fastrtps::rtps::IPLocator::setIPv4(loc, 127, 0, 0, 1);
    loc.port = 7400 + 250 * domain + 10 + 2 * pid;  // RTPS metatraffic unicast port of participant `pid`
    peers.push_back(loc);
  }
  PartListener plistener;
  DomainParticipant* part =
      DomainParticipantFactory::get_instance()->create_participant(
      // without data_on_readers: else the participant listener takes the readers' on_data_available
      domain, pq, &plistener, StatusMask::all() >> StatusMask::data_on_readers());
  if (!part) { std::fprintf(stderr, "fastdds_peer: could not create a participant on domain %d\n", domain); return 1; }
  Subscriber* sub = part->create_subscriber(SUBSCRIBER_QOS_DEFAULT);
  Publisher* pub = part->create_publisher(PUBLISHER_QOS_DEFAULT);
  std::vector<std::unique_ptr<SubListener>> slist;
  std::vector<std::string> registered;
  auto topic_of = [&](const std::string& name, const std::string& type) {
    bool have = false;
    for (auto& t : registered) have = have || t == type;
    if (!have) { TypeSupport ts(new RawType(type)); ts.register_type(part); registered.push_back(type); }
    Topic* t = part->create_topic(name, type, TOPIC_QOS_DEFAULT);
    if (!t) { std::fprintf(stderr, "fastdds_peer: could not create topic %s\n", name.c_str()); std::exit(1); }
    return t;
  };
  auto reader_qos = [&](const std::string& q) {
    DataReaderQos rq = DATAREADER_QOS_DEFAULT;
    apply_qos(q, rq.reliability(), rq.durability(), rq.history());
    rq.endpoint().history_memory_policy = eprosima::fastrtps::rtps::DYNAMIC_REUSABLE_MEMORY_MODE;
    return rq;
  };
  auto writer_qos = [&](const std::string& q) {
    DataWriterQos wq = DATAWRITER_QOS_DEFAULT;
    apply_qos(q, wq.reliability(), wq.durability(), wq.history());
    wq.endpoint().history_memory_policy = eprosima::fastrtps::rtps::DYNAMIC_REUSABLE_MEMORY_MODE;
    return wq;
  };
  for (size_t k = 0; k < subs.size(); ++k) {
    slist.emplace_back(new SubListener(static_cast<int>(k), dir));
    sub->create_datareader(topic_of(subs[k][0], subs[k][1]), reader_qos(subs[k][2]), slist.back().get());
  }
  auto t_end = std::chrono::steady_clock::now() + std::chrono::duration<double>(duration);
  std::vector<std::thread> work;
  std::vector<std::unique_ptr<PubListener>> plist;
  for (auto& p : pubs) {
    plist.emplace_back(new PubListener());
    PubListener* l = plist.back().get();
    DataWriter* w = pub->create_datawriter(topic_of(p[0], p[1]), writer_qos(p[2]), l);
    Bytes data = read_file(p[3]);
    int n = std::stoi(p[4]);
    work.emplace_back([=]() {
      while (l->matched == 0 && std::chrono::steady_clock::now() < t_end)
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
      std::this_thread::sleep_for(std::chrono::milliseconds(500));  // let the reader's side finish matching too
      Bytes d = data;
      for (int i = 0; i < n; ++i) {
        w->write(&d);
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
      }
      out("published " + p[0] + " " + std::to_string(n));
    });
  }
  std::vector<std::unique_ptr<PubListener>> clist;
  std::vector<std::unique_ptr<Reply>> rlist;
  for (auto& c : calls) {
    clist.emplace_back(new PubListener());
    rlist.emplace_back(new Reply());
    PubListener* l = clist.back().get();
    Reply* rl = rlist.back().get();
    DataWriter* w = pub->create_datawriter(topic_of(c[0], c[1]), writer_qos("reliable"), l);
    sub->create_datareader(topic_of(c[2], c[3]), reader_qos("reliable"), rl);
    Bytes req = read_file(c[4]);
    int n = std::stoi(c[5]);
    size_t k = clist.size() - 1;
    work.emplace_back([=]() {
      while ((l->matched == 0 || rl->matched == 0) && std::chrono::steady_clock::now() < t_end)
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      for (int i = 0; i < n && std::chrono::steady_clock::now() < t_end; ++i) {
        Bytes d = req;
        // sequence number (int64 LE at offset 12, after the header's client guid) = i + 1
        int64_t seq = i + 1;
        std::memcpy(d.data() + 12, &seq, 8);
        auto t0 = std::chrono::steady_clock::now();
        w->write(&d);
        auto sent = t0;
        bool done = false;
        while (!done && std::chrono::steady_clock::now() < t_end) {
          // the request topic is volatile: a request written before the server's reader has matched
          // ours (its side of discovery can lag ours under load) is lost, so send it again until
          // answered, as a client that cannot see the server's side would
          if (std::chrono::steady_clock::now() - sent > std::chrono::milliseconds(500)) {
            w->write(&d);
            sent = std::chrono::steady_clock::now();
          }
          {
            std::lock_guard<std::mutex> lk(rl->m);
            for (auto& r : rl->got) {
              if (r.size() >= 20 && std::memcmp(r.data() + 4, d.data() + 4, 16) == 0) {
                done = true;
                if (i == 0) {
                  std::ofstream f(dir + "/reply" + std::to_string(k) + ".bin", std::ios::binary);
                  f.write(reinterpret_cast<const char*>(r.data()), static_cast<std::streamsize>(r.size()));
                }
              }
            }
            rl->got.clear();
          }
          if (!done) std::this_thread::sleep_for(std::chrono::microseconds(50));
        }
        double us = std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count();
        out(std::string(done ? "reply " : "noreply ") + std::to_string(k) + " " + std::to_string(i) + " " +
            std::to_string(us));
        if (!done) break;
      }
    });
  }
  for (auto& t : work) t.join();
  while (std::chrono::steady_clock::now() < t_end) std::this_thread::sleep_for(std::chrono::milliseconds(20));
  part->delete_contained_entities();
  DomainParticipantFactory::get_instance()->delete_participant(part);
  out("done");
  return 0;
}
